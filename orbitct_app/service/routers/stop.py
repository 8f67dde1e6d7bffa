"""``POST /stop``: emergency stop, halting every axis and switching X-rays off; always accepted, never queued."""

from __future__ import annotations

import asyncio
import logging

from fastapi import APIRouter
from pydantic import BaseModel, Field

from orbitct_app.service.core.errors import ERROR_RESPONSES
from orbitct_app.service.deps import ServiceDep, Stopper

router = APIRouter(tags=["stop"], responses=ERROR_RESPONSES)
log = logging.getLogger("orbitct.service.stop")
CONFIRM_TIMEOUT_S = 5.0


class StopOut(BaseModel):
    """What the emergency stop did."""

    model_config = {"json_schema_extra": {"examples": [
        {"accepted": True, "halted": True, "scan_aborted": "a1b2c3d4e5f60718", "message": "every axis halted, X-rays off"}
    ]}}

    accepted: bool = True
    halted: bool = Field(description="the bench confirmed: every axis halted and X-rays off")
    scan_aborted: str | None = Field(None, description="id of the scan that was aborted, if one ran")
    message: str


@router.post("/stop", response_model=StopOut, status_code=202, summary="Emergency stop")
async def emergency_stop(service: ServiceDep, who: Stopper) -> StopOut:
    """Abort any scan, halt every axis and switch X-rays off. Any valid token may stop the bench.

    Runs on the web server's loop (never in the worker thread pool) and takes no lock a scan holds.
    """
    log.warning("emergency stop by %s (%s)", who.name, who.role)
    scan_id, future = service.rig.emergency_stop(f"emergency stop by {who.name}")
    if future is None:
        return StopOut(halted=False, scan_aborted=scan_id, message=f"bench not connected ({service.rig.connection_state}); abort requested")
    try:
        await asyncio.wait_for(asyncio.wrap_future(future), CONFIRM_TIMEOUT_S)
    except asyncio.TimeoutError:
        return StopOut(halted=False, scan_aborted=scan_id, message=f"halt sent; not confirmed within {CONFIRM_TIMEOUT_S:g} s")
    except Exception as exc:  # noqa: BLE001 - the stop is still accepted; say what the bench answered
        return StopOut(halted=False, scan_aborted=scan_id, message=f"halt sent; the bench reported: {exc}")
    return StopOut(halted=True, scan_aborted=scan_id, message="every axis halted, X-rays off")
