"""GCS 2.0 controller twins (hexapod, rotation stage) served on loopback TCP and pseudo-terminals."""

from __future__ import annotations

import threading
from typing import Any

from devices.twins.gcs.controller import GcsController
from devices.twins.gcs.faults import Faults
from devices.twins.gcs.hexapod import HexapodController
from devices.twins.gcs.rotation_stage import RotationStageController
from devices.twins.gcs.server import TwinServer
from devices.twins.world import get_world

CONTROLLERS: dict[str, type[GcsController]] = {"hexapod": HexapodController, "rotation_stage": RotationStageController}
_SIM: dict[tuple[str, str], TwinServer] = {}
_SIM_LOCK = threading.Lock()


def make_controller(kind: str, world: str | None = "bench", **options: Any) -> GcsController:
    """A controller twin of ``kind`` ('hexapod' or 'rotation_stage') writing its true state to ``world``."""
    try:
        cls = CONTROLLERS[kind.replace("-", "_")]
    except KeyError:
        raise ValueError(f"GCS twin kind must be one of {sorted(CONTROLLERS)}, got {kind!r}") from None
    return cls(get_world(world) if world else None, **options)  # type: ignore[call-arg]


def start_twin(kind: str, host: str = "127.0.0.1", port: int = 0, world: str | None = "bench", **options: Any) -> TwinServer:
    """Start a twin server of ``kind`` on ``host:port`` (0 = a free port) in a background thread."""
    return TwinServer(make_controller(kind, world, **options), host, port).start()


def sim_server(kind: str, world: str = "bench", **options: Any) -> TwinServer:
    """The in-process twin of ``kind`` for ``sim://world`` (started on first use; options apply then)."""
    key = (kind.replace("-", "_"), world)
    with _SIM_LOCK:
        server = _SIM.get(key)
        if server is None:
            server = _SIM[key] = start_twin(kind, world=world, **options)
        return server


def stop_sim_servers() -> None:
    """Stop every in-process ``sim://`` twin (tests use this for a fresh bench)."""
    with _SIM_LOCK:
        for server in _SIM.values():
            server.stop()
        _SIM.clear()


__all__ = ["CONTROLLERS", "Faults", "HexapodController", "RotationStageController", "TwinServer",
           "make_controller", "sim_server", "start_twin", "stop_sim_servers"]
