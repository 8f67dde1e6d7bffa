"""``/health``: liveness without a token (no details that help an attacker)."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel

from orbitct import __version__
from orbitct_app.service.deps import ServiceDep

router = APIRouter(tags=["health"])


class Health(BaseModel):
    """Whether the service is up and the bench is connected."""

    status: str
    version: str
    bench: str


@router.get("/health", response_model=Health, summary="Liveness and bench connection")
async def health(service: ServiceDep) -> Health:
    """``ok`` when the bench is connected, ``degraded`` otherwise."""
    bench = service.rig.connection_state.split(":")[0]  # the reason stays behind authentication
    return Health(status="ok" if bench == "connected" else "degraded", version=__version__, bench=bench)
