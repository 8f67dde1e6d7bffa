"""GCS 2.0 controller twins (hexapod, rotation stage) served on loopback TCP and pseudo-terminals."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from devices.twins.gcs.controller import GcsController
from devices.twins.gcs.hexapod import HexapodController
from devices.twins.gcs.rotation_stage import RotationStageController
from devices.twins.gcs.server import GcsTwin
from devices.twins.runtime import TwinThread
from devices.twins.world import get_world

CONTROLLERS: dict[str, Callable[..., GcsController]] = {
    "hexapod": HexapodController,
    "rotation_stage": RotationStageController,
}


def make_controller(kind: str, world: str | None = "bench", **options: Any) -> GcsController:
    """A controller twin of ``kind`` ('hexapod' or 'rotation_stage') writing its true state to ``world``."""
    try:
        cls = CONTROLLERS[kind.replace("-", "_")]
    except KeyError:
        raise ValueError(f"GCS twin kind must be one of {sorted(CONTROLLERS)}, got {kind!r}") from None
    return cls(get_world(world) if world else None, **options)


def start_twin(
    kind: str, host: str = "127.0.0.1", port: int = 0, world: str | None = "bench", **options: Any
) -> TwinThread:
    """Start a twin of ``kind`` on ``host:port`` (0 = a free port) in a background thread."""
    return TwinThread(GcsTwin(make_controller(kind, world, **options)), host, port)


__all__ = ["CONTROLLERS", "GcsTwin", "HexapodController", "RotationStageController", "make_controller", "start_twin"]
