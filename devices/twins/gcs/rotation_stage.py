"""Rotation-stage twin (one rotary axis '1' in degrees, C-863-like controller) with hidden errors.

The true angle differs from the encoder by a fixed zero offset, backlash that
depends on the last direction of travel, and a once-per-turn eccentricity error.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from devices.gcs import errors as E
from devices.twins.gcs.controller import GcsController, GcsError, Reply, Session
from devices.twins.runtime import TwinFaults
from devices.twins.world import SimWorld


class RotationStageController(GcsController):
    """Single-axis rotation stage controller twin."""

    idn = "(c)2026 Physik Instrumente (PI) GmbH & Co. KG, C-863.12, 0126000002, 01.200"
    reference_pose = (0.0,)
    command_names = GcsController.command_names + ("VEL", "VEL?")
    max_velocity = 360.0  # deg/s

    def __init__(
        self,
        world: SimWorld | None = None,
        *,
        time_scale: float = 1.0,
        imperfect: bool = True,
        seed: int = 11,
        faults: TwinFaults | None = None,
        velocity: float = 30.0,
        low_deg: float = -370.0,
        high_deg: float = 370.0,
    ) -> None:
        super().__init__(("1",), ("deg",), (low_deg,), (high_deg,), (17.3,), time_scale=time_scale, faults=faults)
        self.world = world
        self.velocity = float(velocity)
        rng = np.random.default_rng(seed)
        on = 1.0 if imperfect else 0.0
        self.zero_offset_deg = on * float(rng.normal(0.0, 0.01))
        self.backlash_deg = on * 0.003
        self.eccentricity_deg = on * 0.004
        self.eccentricity_phase = float(rng.uniform(0, 2 * math.pi))
        self.noise = on * 2e-5
        self._rng = np.random.default_rng(seed + 1)

    def speeds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return np.array([self.velocity]), np.array([4.0 * self.velocity])

    def reference_speeds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return np.array([20.0]), np.array([80.0])

    def true_angle_deg(self) -> float:
        """Mechanical angle (deg) including the hidden errors."""
        enc = float(self.motion.position()[0])
        return (
            enc
            + self.zero_offset_deg
            - 0.5 * self.backlash_deg * float(self.motion.last_direction[0])
            + self.eccentricity_deg * math.sin(math.radians(enc) + self.eccentricity_phase)
        )

    def readback(self) -> NDArray[np.float64]:
        return self.motion.position() + self._rng.normal(0.0, self.noise, 1) * self.referenced

    def publish(self) -> None:
        if self.world is None:
            return
        with self.world.lock:
            self.world.stage_true_rad = math.radians(self.true_angle_deg())

    def _vel(self, s: Session, a: list[str]) -> Reply:
        pairs = self._pairs(a)
        for _, v in pairs:
            if not 0.0 < v <= self.max_velocity:
                raise GcsError(E.PARAM_OUT_OF_RANGE)
        self.velocity = pairs[-1][1]
        return None

    def _vel_q(self, s: Session, a: list[str]) -> Reply:
        return self._axis_reply(self._axis_list(a), [self.velocity])
