"""``/health``: liveness without a token (no details that help an attacker)."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from orbitct import __version__
from orbitct_app.service.deps import ServiceDep

router = APIRouter(tags=["health"])


class Health(BaseModel):
    """Whether the service is up, the bench connected, the guard listening and an emergency stop latched."""

    status: str
    version: str
    bench: str
    guard: str = Field(description="the stop listener: listening, starting, restarting or failed")
    estop: str = Field(description="latched (no motion or X-rays until an operator resets it) or clear")
    jobs: str = Field(
        description="the Dask cluster jobs run on: starting, connected, failed (could not be started or "
        "reached) or lost (went away; running jobs failed, queued ones wait)"
    )
    disk: str = Field(
        description="the data directory's disk: ok, low (less free than the bench's storage.reserve_mb: "
        "scans are refused) or full (under 4 MB: nothing can be recorded)"
    )


@router.get("/health", response_model=Health, summary="Liveness, bench connection and emergency-stop latch")
async def health(service: ServiceDep) -> Health:
    """``ok`` when the bench is connected, the guard listens, no stop is latched and the disk has room; ``degraded``
    otherwise."""
    bench = service.rig.connection_state.split(":")[0]  # the reasons stay behind authentication
    guard = service.guard.state.split(":")[0]
    latched = service.latch.latched
    disk, _ = service.disk()
    ok = bench == "connected" and guard == "listening" and not latched and disk == "ok"
    return Health(
        status="ok" if ok else "degraded",
        version=__version__,
        bench=bench,
        guard=guard,
        estop="latched" if latched else "clear",
        disk=disk,
        jobs=service.jobs.engine_state.split(":")[0],
    )
