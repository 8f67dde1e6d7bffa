"""``/stop``: the emergency stop (any token), its latch (``GET``), its reset (operator) and its events.

The fastest stop is the guard's own listener (``stop_url`` in ``GET /stop``; ``orbitct stop``):
it never shares a server with status polling. ``POST /stop`` here forwards to it.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Header, Request
from pydantic import BaseModel, ConfigDict, Field

from orbitct_app.service.core.errors import ERROR_RESPONSES, Conflict, ErrorBody
from orbitct_app.service.core.events import sse_response
from orbitct_app.service.deps import Reader, Resetter, ServiceDep, Stopper
from orbitct_app.service.safety.estop import TOPIC
from orbitct_app.service.safety.latch import NotLatchedError
from orbitct_app.service.safety.request import stop_reason

router = APIRouter(prefix="/stop", tags=["stop"], responses=ERROR_RESPONSES)


class StopRequest(BaseModel):
    """Why the bench is stopped (optional). A stop is never refused for its reason: longer text is cut to 500
    characters and unknown fields are ignored."""

    model_config = ConfigDict(extra="ignore", allow_inf_nan=False)
    reason: str = Field("", description="shown with the latch; cut to 500 characters")


class HaltCheckOut(BaseModel):
    """One device after the stop: proven halted or not, what was read back, what went wrong."""

    device: str
    halted: bool
    verified: str = ""
    problem: str = ""


class StopOut(BaseModel):
    """What the emergency stop did and what it proved."""

    model_config = {
        "json_schema_extra": {
            "examples": [
                {
                    "accepted": True,
                    "halted": True,
                    "latched": True,
                    "via": "guard",
                    "scan_aborted": "a1b2c3d4e5f60718",
                    "by": "alice (viewer)",
                    "reason": "emergency stop by alice",
                    "message": "halted and verified: hexapod axes not moving; rotation_stage axes not moving; xray high voltage off, "
                    "not exposing (state IDLE)",
                    "devices": [
                        {
                            "device": "xray",
                            "halted": True,
                            "verified": "high voltage off, not exposing (state IDLE)",
                            "problem": "",
                        }
                    ],
                }
            ]
        }
    }

    accepted: bool = True
    halted: bool = Field(description="every device was read back halted: axes not moving, high voltage off")
    latched: bool = Field(description="the stop is latched: no scan, move or referencing until an operator resets it")
    via: str = Field(description="guard (its own connections), rig (the rig process's links) or none")
    scan_aborted: str | None = Field(None, description="id of the scan that was running, now aborted")
    by: str = ""
    reason: str = ""
    message: str
    devices: list[HaltCheckOut] = []
    latch_recorded: bool = Field(
        True,
        description="the latch is written to the data directory (it survives a "
        "restart); false while it holds in memory only",
    )
    latch_problem: str | None = Field(None, description="why the latch could not be written yet (retried)")
    note: str | None = Field(None, description="what was wrong with the request; the stop was taken all the same")


class LatchOut(BaseModel):
    """The emergency-stop latch and where the stop listener is."""

    latched: bool
    since_utc: str | None = None
    by: str | None = None
    reason: str | None = None
    last_reset: dict[str, Any] | None = None
    stop_url: str | None = Field(None, description="the guard's own stop listener (POST, any token)")
    guard: str = ""
    recorded: bool = Field(True, description="the latch's state is written to the data directory")
    record_problem: str | None = Field(None, description="why it could not be written yet (retried)")


class ResetRequest(BaseModel):
    """A note for the log (what was checked before resetting)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)
    note: str = Field("", max_length=500)


@router.post(
    "",
    response_model=StopOut,
    status_code=202,
    summary="Emergency stop",
    openapi_extra={
        "requestBody": {"required": False, "content": {"application/json": {"schema": StopRequest.model_json_schema()}}}
    },
)
async def emergency_stop(request: Request, service: ServiceDep, who: Stopper) -> StopOut:
    """Latch the stop, abort any scan, halt every axis and switch X-rays off, then read every device back.

    ``halted`` is true only when each device's stop was acknowledged and its read-back confirms it;
    otherwise ``message`` and ``devices`` say what could not be verified. Any valid token may stop. The body is
    optional, and a stop is never refused for it: a body that is not a ``StopRequest`` is noted in ``note``.
    """
    reason, problem = stop_reason(await request.body())
    reply = await service.estop.stop(who, reason, request.headers.get("authorization"))
    if problem:
        reply["note"] = f"{problem}; the stop was taken"
    return StopOut(**reply)


@router.get("", response_model=LatchOut, summary="Emergency-stop latch")
async def latch_state(service: ServiceDep, _: Reader) -> LatchOut:
    """Whether a stop is latched, since when, by whom and why; the last reset; the stop listener's URL."""
    return LatchOut(**service.estop.state())


@router.post(
    "/reset",
    response_model=LatchOut,
    summary="Reset the emergency stop (operator)",
    responses={409: {"model": ErrorBody, "description": "no stop is latched"}},
)
async def reset(service: ServiceDep, who: Resetter, body: ResetRequest | None = None) -> LatchOut:
    """Clear the latch after checking the bench; logged with who and when. Nothing moves and X-rays stay off."""
    try:
        return LatchOut(**service.estop.reset(who, (body or ResetRequest()).note))
    except NotLatchedError as exc:
        raise Conflict(str(exc), advice="there is nothing to reset") from None


@router.get(
    "/events",
    summary="Stops and resets (server-sent events)",
    responses={
        200: {
            "content": {
                "text/event-stream": {
                    "example": 'event: latch\ndata: {"latched":false}\n\n'
                    'id: 3\nevent: stop\ndata: {"halted":true,"latched":true}\n\n'
                }
            }
        }
    },
)
def stop_events(service: ServiceDep, _: Reader, last_event_id: Annotated[str | None, Header(max_length=20)] = None):
    """First ``latch`` (the latch as ``GET /stop`` gives it, without an id), then the events ``stop`` (with what was
    verified) and ``reset`` (who, when), in order; resumes after ``Last-Event-ID``. The stream stays open."""
    return sse_response(service.bus, TOPIC, last_event_id, first=("latch", service.estop.state()))
