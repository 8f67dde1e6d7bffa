"""Open any orbitct device by kind and URI, and stop them all at once.

Kinds map to lazy ``"module:Class"`` strings so a bench without, say, the
Modbus stack installed can still open its motion devices.
"""

from __future__ import annotations

import asyncio
import importlib
from collections.abc import Iterable
from typing import Any

from devices.errors import DeviceError

REGISTRY: dict[str, str] = {
    "hexapod": "devices.hexapod:Hexapod",
    "rotation_stage": "devices.rotation_stage:RotationStage",
    "xray": "devices.xray:XrayGenerator",
    "detector": "devices.detector:Detector",
    "carm": "devices.carm:CArm",
}


def device_class(kind: str) -> type:
    """The driver class registered for ``kind`` (``rotation-stage`` and ``rotation_stage`` both work)."""
    key = kind.replace("-", "_").lower()
    target = REGISTRY.get(key)
    if target is None:
        raise DeviceError(f"unknown device kind {kind!r}; kinds are {', '.join(sorted(REGISTRY))}")
    module, attr = target.split(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise DeviceError(f"device kind {kind!r}: cannot load {target} ({exc})") from None


async def open_device(kind: str, name: str, uri: str, **options: Any) -> Any:
    """Create the driver for ``kind`` at ``uri`` and connect it."""
    device = device_class(kind)(name, uri, **options)
    await device.connect()
    return device


async def stop_all(devices: Iterable[Any]) -> list[BaseException]:
    """Halt every axis and switch X-rays off on all devices at once; returns the errors (none raised).

    Every device gets its stop (``#24`` on GCS controllers) concurrently, so the
    whole bench is halted within one command round trip.
    """
    actions = []
    for dev in devices:
        if hasattr(dev, "xray_off"):
            actions.append(dev.xray_off())
        if hasattr(dev, "stop"):
            actions.append(dev.stop())
    results = await asyncio.gather(*actions, return_exceptions=True)
    return [r for r in results if isinstance(r, BaseException)]
