"""Shared physical state of the in-process twins of one simulated bench.

The motion twins write their *true* (not read-back) state here; the detector
twin reads it to render each frame at the true object pose. Worlds are looked
up by name, so ``sim://bench`` devices in one process share one world.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from orbitct.kinematics import object_pose


@dataclass
class SimWorld:
    """True state of a simulated bench: stage angle (rad), hexapod pose (mm, rad), X-ray settings."""

    name: str = "bench"
    stack_order: str = "stage_on_hexapod"
    pivot_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    stage_true_rad: float = 0.0
    hexapod_true: NDArray[np.float64] = field(default_factory=lambda: np.zeros(6))
    xray_kv: float = 90.0
    xray_ma: float = 1.0
    exposure_ms: float = 10.0
    exposing: bool = False
    xray_frame_counter: int = 0  # completed exposures (the detector twin's hardware trigger)
    lock: threading.RLock = field(default_factory=threading.RLock, repr=False)

    def object_pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """True object pose ``(R, t)`` in the lab frame now."""
        with self.lock:
            return object_pose(
                self.stage_true_rad, self.hexapod_true.copy(), order=self.stack_order, pivot=self.pivot_mm
            )


_WORLDS: dict[str, SimWorld] = {}
_LOCK = threading.Lock()


def get_world(name: str = "bench") -> SimWorld:
    """The world called ``name`` (created on first use)."""
    with _LOCK:
        if name not in _WORLDS:
            _WORLDS[name] = SimWorld(name=name)
        return _WORLDS[name]


def reset_world(name: str = "bench") -> SimWorld:
    """Replace the world called ``name`` by a fresh one."""
    with _LOCK:
        _WORLDS[name] = SimWorld(name=name)
        return _WORLDS[name]
