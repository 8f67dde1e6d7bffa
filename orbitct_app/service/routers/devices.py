"""``/devices``: list, state, referencing, maintenance moves and per-device stop (all through the bench loop)."""

from __future__ import annotations

import logging
import math
from typing import Annotated, Any

from fastapi import APIRouter, Path
from pydantic import BaseModel, ConfigDict, Field, field_validator

from orbitct_app.service.core.errors import (
    BENCH_UNAVAILABLE,
    ERROR_RESPONSES,
    Conflict,
    ErrorBody,
    FieldProblem,
    Invalid,
    StopLatched,
)
from orbitct_app.service.deps import Operator, Reader, ServiceDep
from orbitct_app.service.rig.status import device_status

log = logging.getLogger("orbitct.service.devices")
router = APIRouter(prefix="/devices", tags=["devices"], responses={**ERROR_RESPONSES, **BENCH_UNAVAILABLE})
DeviceName = Annotated[str, Path(max_length=40, pattern=r"^[A-Za-z0-9_-]+$")]
MOVE_TIMEOUT_S = 120.0


class AxisOut(BaseModel):
    """One axis with unit and soft limits."""

    name: str
    unit: str
    low: float
    high: float


class DeviceOut(BaseModel):
    """A connected device."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "name": "hexapod",
                    "model": "C-887 (twin)",
                    "serial": "SIM-0001",
                    "firmware": "1.0",
                    "uri": "sim://bench",
                    "axes": [{"name": "X", "unit": "mm", "low": -50, "high": 50}],
                }
            ]
        }
    )

    name: str
    model: str
    serial: str
    firmware: str = ""
    uri: str = ""
    axes: list[AxisOut] = []


class AxisStatus(BaseModel):
    """One axis in the operator's terms: position, target and soft limits with the axis unit."""

    axis: str
    unit: str
    position: str = Field(description="e.g. '1.250 mm'; '—' when not read")
    target: str
    limits: str = Field(description="soft limits, e.g. '-50 … 50 mm'")
    referenced: bool
    on_target: bool
    moving: bool


class Reading(BaseModel):
    """A labelled reading with its unit (kV, mA, ms, pixels, degrees)."""

    label: str
    value: str


class DeviceState(BaseModel):
    """A device and what it reads now (positions, on target, referenced; X-ray state), and the emergency-stop latch.

    ``status`` names the state in the operator's terms (``latched``, ``fault``, ``moving``, ``exposing``, ``high
    voltage on``, ``not referenced``, ``servo off``, ``on target``, ``referenced``, ``ready``, ``armed``, ``door
    open``, ``standby``), ``why`` says why, ``tone`` is how the console colours it; ``state`` is the raw read-back.
    """

    device: DeviceOut
    status: str = ""
    tone: str = Field("idle", description="alarm (red), ok (green) or idle (plain)")
    why: str = ""
    axes: list[AxisStatus] = []
    readings: list[Reading] = []
    state: dict[str, Any]
    estop_latched: bool = Field(False, description="an emergency stop is latched: no motion or X-rays until reset")


class MoveRequest(BaseModel):
    """Absolute targets per axis, in the axis unit (mm or deg); checked against the limits before moving."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        allow_inf_nan=False,
        json_schema_extra={"examples": [{"targets": {"X": 1.0, "U": 0.5}}]},
    )

    targets: dict[Annotated[str, Field(pattern=r"^[A-Za-z0-9]{1,8}$")], Annotated[float, Field(ge=-1e5, le=1e5)]] = (
        Field(min_length=1, max_length=6)
    )

    @field_validator("targets")
    @classmethod
    def _finite(cls, v: dict[str, float]) -> dict[str, float]:
        for axis, value in v.items():
            if not math.isfinite(value):
                raise ValueError(f"target of axis {axis} must be a finite number")
        return v


def _state(service: Any, result: dict[str, Any]) -> DeviceState:
    latched = service.latch.latched
    named = device_status(result["device"], result["state"], latched)
    return DeviceState(device=DeviceOut(**result["device"]), state=result["state"], estop_latched=latched, **named)


def _idle(service: Any, action: str) -> None:
    refused = service.estop.refusal(action)
    if refused:
        raise StopLatched(refused)
    if service.rig.busy is not None:
        raise Conflict(f"the bench is running scan {service.rig.busy}", advice=f"wait until it ends for {action}")


@router.get("", response_model=list[DeviceOut], summary="List devices")
async def list_devices(service: ServiceDep, _: Reader) -> list[DeviceOut]:
    """Every connected device with its axes, units and soft limits."""
    return [DeviceOut(**d) for d in await service.rig.run("describe")]


@router.get("/{name}", response_model=DeviceState, summary="State of a device")
async def get_device(name: DeviceName, service: ServiceDep, _: Reader) -> DeviceState:
    """Description and current read-back."""
    return _state(service, await service.rig.run("device_state", name=name))


@router.post(
    "/{name}/reference",
    response_model=DeviceState,
    summary="Reference a motion device",
    responses={409: {"model": ErrorBody, "description": "a scan is running, or an emergency stop is latched"}},
)
async def reference(name: DeviceName, service: ServiceDep, _: Operator) -> DeviceState:
    """Servo on and reference every axis; returns when done."""
    _idle(service, "referencing")
    return _state(service, await service.rig.run("reference", timeout_s=MOVE_TIMEOUT_S, name=name))


@router.post(
    "/{name}/move",
    response_model=DeviceState,
    summary="Maintenance move",
    responses={
        409: {
            "model": ErrorBody,
            "description": "a scan is running, the device is not referenced, or an emergency stop is latched",
        }
    },
)
async def move(name: DeviceName, body: MoveRequest, service: ServiceDep, _: Operator) -> DeviceState:
    """Absolute move of some axes; limits (and the hexapod workspace) are checked before anything moves."""
    _idle(service, "moves")
    try:
        return _state(service, await service.rig.run("move", timeout_s=MOVE_TIMEOUT_S, name=name, targets=body.targets))
    except Invalid as exc:
        raise Invalid(exc.message, details=[FieldProblem(field="targets", reason=exc.message)]) from None


@router.post("/{name}/stop", response_model=DeviceState, summary="Stop one device")
async def stop_device(name: DeviceName, service: ServiceDep, _: Operator) -> DeviceState:
    """Halt the device's axes (X-ray generator: X-rays off). For everything at once use ``POST /stop``."""
    return _state(service, await service.rig.run("stop_device", name=name))


@router.post(
    "/{name}/reset-fault",
    response_model=DeviceState,
    summary="Reset a generator fault",
    responses={
        409: {
            "model": ErrorBody,
            "description": "the fault's cause persists (door open, fault input), or a scan is running",
        }
    },
)
async def reset_fault(name: DeviceName, service: ServiceDep, who: Operator) -> DeviceState:
    """Clear the X-ray generator's latched fault once its cause is gone; refused, naming the cause, while it persists.

    Allowed while an emergency stop is latched: it switches nothing on.
    """
    if service.rig.busy is not None:
        raise Conflict(f"the bench is running scan {service.rig.busy}", advice="reset the fault when it has ended")
    result = _state(service, await service.rig.run("reset_fault", name=name))
    log.warning("generator fault on %s reset by %s (%s)", name, who.name, who.role)
    return result
