"""Open any orbitct device by kind and URI, and stop them all at once.

The driver class follows from the kind and the URI's scheme (a ``folder://`` detector is a
:class:`~devices.folder_detector.FolderWatchDetector`); a ``sim://`` URI first starts the
kind's twin (:mod:`devices.sim`) and the driver connects to the twin's loopback endpoint.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Iterable
from typing import Any

from devices import sim
from devices.carm import CArm
from devices.detector import Detector
from devices.errors import DeviceError, UriError
from devices.folder_detector import FolderWatchDetector
from devices.hexapod import Hexapod
from devices.rotation_stage import RotationStage
from devices.uri import parse_uri
from devices.xray import XrayGenerator

# kind -> URI scheme -> driver class
DRIVERS: dict[str, dict[str, type]] = {
    "hexapod": {"tcp": Hexapod, "serial": Hexapod},
    "rotation_stage": {"tcp": RotationStage, "serial": RotationStage},
    "xray": {"modbus": XrayGenerator, "tcp": XrayGenerator},
    "detector": {"tcp": Detector, "folder": FolderWatchDetector},
    "carm": {"tcp": CArm},
}


def _kind(kind: str) -> str:
    key = kind.replace("-", "_").lower()
    if key not in DRIVERS:
        raise DeviceError(f"unknown device kind {kind!r}; kinds are {', '.join(sorted(DRIVERS))}")
    return key


def device_class(kind: str, scheme: str = "tcp") -> type:
    """The driver class for ``kind`` at a URI of ``scheme`` (``rotation-stage`` and ``rotation_stage`` both work)."""
    by_scheme = DRIVERS[_kind(kind)]
    if scheme not in by_scheme:
        allowed = ", ".join(f"{s}://" for s in (*by_scheme, "sim"))
        raise UriError(f"a {kind} connects by {allowed}; not {scheme}://")
    return by_scheme[scheme]


async def open_device(kind: str, name: str, uri: str, **options: Any) -> Any:
    """Create the driver for ``kind`` at ``uri`` and connect it (``sim://`` starts the kind's twin first)."""
    key = _kind(kind)
    twin = None
    if parse_uri(uri).scheme == "sim":
        twin, options = sim.start_twin(key, uri, options)
        uri = twin.endpoint
    try:
        device = device_class(key, parse_uri(uri).scheme)(name, uri, **options)
    except BaseException:
        if twin is not None and twin.kind not in sim.SHARED_KINDS:
            twin.stop()
        raise
    if twin is not None:
        sim.attach(device, twin)
    try:
        await device.connect()
    except BaseException:
        with contextlib.suppress(Exception):
            await device.close()
        raise
    return device


@contextlib.asynccontextmanager
async def opened(kind: str, name: str, uri: str, **options: Any) -> AsyncIterator[Any]:
    """:func:`open_device` as an ``async with`` block; the device (and a twin of its own) closes at the end."""
    device = await open_device(kind, name, uri, **options)
    try:
        yield device
    finally:
        await device.close()


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
