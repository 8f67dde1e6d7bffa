"""``/devices``: list, state, referencing, maintenance moves and per-device stop (all through the bench loop)."""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable
from dataclasses import asdict
from typing import Annotated, Any

from fastapi import APIRouter, Path
from pydantic import BaseModel, ConfigDict, Field, field_validator

from orbitct.service.deps import Operator, Reader, ServiceDep
from orbitct.service.errors import ERROR_RESPONSES, ApiError, Conflict, FieldProblem, Invalid, NotFound, Unavailable

router = APIRouter(prefix="/devices", tags=["devices"], responses=ERROR_RESPONSES)
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

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "name": "hexapod", "model": "C-887 (twin)", "serial": "SIM-0001", "firmware": "1.0", "uri": "sim://bench",
        "axes": [{"name": "X", "unit": "mm", "low": -50, "high": 50}]}]})

    name: str
    model: str
    serial: str
    firmware: str = ""
    uri: str = ""
    axes: list[AxisOut] = []


class DeviceState(BaseModel):
    """A device and what it reads now (positions, on target, referenced; X-ray state)."""

    device: DeviceOut
    state: dict[str, Any]


class MoveRequest(BaseModel):
    """Absolute targets per axis, in the axis unit (mm or deg); checked against the limits before moving."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"targets": {"X": 1.0, "U": 0.5}}]})

    targets: dict[Annotated[str, Field(pattern=r"^[A-Za-z0-9]{1,8}$")], Annotated[float, Field(ge=-1e5, le=1e5)]] = Field(
        min_length=1, max_length=6)

    @field_validator("targets")
    @classmethod
    def _finite(cls, v: dict[str, float]) -> dict[str, float]:
        for axis, value in v.items():
            if not math.isfinite(value):
                raise ValueError(f"target of axis {axis} must be a finite number")
        return v


def _out(info: Any) -> DeviceOut:
    d = asdict(info)
    return DeviceOut(name=d["name"], model=d["model"], serial=d["serial"], firmware=d.get("firmware", ""),
                     uri=str(d.get("uri", "")), axes=[AxisOut(**a) for a in d.get("axes", ())])


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


async def _on_device(service: Any, name: str, action: Callable[[Any], Awaitable[Any]], timeout_s: float = 30.0) -> Any:
    """Run ``action(device)`` on the bench loop; device errors become clear 4xx/503 answers."""
    from devices.errors import (DeviceError, DeviceTimeoutError, FaultActiveError, InterlockOpenError,
                                NotConnectedError, NotReferencedError, OutOfLimitsError)

    def pick(bench: Any) -> Any:
        devices = service.bench.device_map()
        if name not in devices:
            raise NotFound(f"no device {name!r}; known: {', '.join(devices) or 'none'}")
        return action(devices[name])

    try:
        return await service.bench.run(pick, timeout_s)
    except ApiError:
        raise
    except OutOfLimitsError as exc:
        raise Invalid(str(exc), details=[FieldProblem(field="targets", reason=str(exc))]) from None
    except (NotReferencedError, InterlockOpenError, FaultActiveError) as exc:
        raise Conflict(str(exc)) from None
    except (DeviceTimeoutError, NotConnectedError) as exc:
        raise Unavailable(f"{name}: {exc}") from None
    except DeviceError as exc:
        raise Conflict(f"{name} refused: {exc}") from None


def _idle(service: Any) -> None:
    if service.bench.busy is not None:
        raise Conflict(f"the bench is running scan {service.bench.busy}; maintenance moves wait until it ends")


@router.get("", response_model=list[DeviceOut], summary="List devices")
async def list_devices(service: ServiceDep, _: Reader) -> list[DeviceOut]:
    """Every connected device with its axes, units and soft limits."""
    async def describe_all(bench: Any) -> list[Any]:
        return [await d.describe() for d in service.bench.device_map().values()]

    return [_out(i) for i in await service.bench.run(describe_all)]


@router.get("/{name}", response_model=DeviceState, summary="State of a device")
async def get_device(name: DeviceName, service: ServiceDep, _: Reader) -> DeviceState:
    """Description and current read-back."""
    async def both(dev: Any) -> tuple[Any, Any]:
        return await dev.describe(), await dev.read()

    info, state = await _on_device(service, name, both)
    return DeviceState(device=_out(info), state=_plain(state))


@router.post("/{name}/reference", response_model=DeviceState, summary="Reference a motion device",
             responses={409: {"description": "a scan is running"}})
async def reference(name: DeviceName, service: ServiceDep, _: Operator) -> DeviceState:
    """Servo on and reference every axis; returns when done."""
    _idle(service)

    async def do(dev: Any) -> tuple[Any, Any]:
        if not hasattr(dev, "reference"):
            raise Invalid(f"device {name} has no axes to reference")
        await dev.reference()
        return await dev.describe(), await dev.read()

    info, state = await _on_device(service, name, do, MOVE_TIMEOUT_S)
    return DeviceState(device=_out(info), state=_plain(state))


@router.post("/{name}/move", response_model=DeviceState, summary="Maintenance move",
             responses={409: {"description": "a scan is running, or the device is not referenced"}})
async def move(name: DeviceName, body: MoveRequest, service: ServiceDep, _: Operator) -> DeviceState:
    """Absolute move of some axes; limits (and the hexapod workspace) are checked before anything moves."""
    _idle(service)

    async def do(dev: Any) -> tuple[Any, Any]:
        if not hasattr(dev, "move"):
            raise Invalid(f"device {name} has no axes to move")
        known = {a.name for a in (await dev.describe()).axes}
        unknown = sorted(set(body.targets) - known)
        if unknown:
            raise Invalid(f"unknown axes {unknown}", details=[FieldProblem(field=f"targets.{a}", reason=f"{name} has axes {sorted(known)}") for a in unknown])
        await dev.move(body.targets)
        return await dev.describe(), await dev.read()

    info, state = await _on_device(service, name, do, MOVE_TIMEOUT_S)
    return DeviceState(device=_out(info), state=_plain(state))


@router.post("/{name}/stop", response_model=DeviceState, summary="Stop one device")
async def stop_device(name: DeviceName, service: ServiceDep, _: Operator) -> DeviceState:
    """Halt the device's axes (X-ray generator: X-rays off). For everything at once use ``POST /stop``."""
    async def do(dev: Any) -> tuple[Any, Any]:
        if hasattr(dev, "xray_off"):
            await dev.xray_off()
        elif hasattr(dev, "stop"):
            await dev.stop()
        return await dev.describe(), await dev.read()

    info, state = await _on_device(service, name, do)
    return DeviceState(device=_out(info), state=_plain(state))
