"""Hexapod twin (C-887 style): six legs, coupled workspace, pivot point, hidden mechanical errors.

Axes X, Y, Z (mm) and U, V, W (deg), rotation ``R_x(U) R_y(V) R_z(W)`` about the
pivot point set with ``SPI`` (R, S, T in mm). A pose is reachable when every
axis is inside TMN?/TMX? and every leg length lies inside the leg stroke; the
legs join a base ring and a platform ring as on a Stewart platform.

The true pose (what the detector twin images) differs from the encoder
read-back by fixed encoder offsets, backlash that depends on the last direction
of travel, and a gravity sag that grows with tilt.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from devices.gcs import errors as E
from devices.twins.gcs.controller import GcsController, GcsError, Reply, Session
from devices.twins.runtime import TwinFaults
from devices.twins.world import SimWorld
from orbitct.kinematics import hexapod_transform

AXES = ("X", "Y", "Z", "U", "V", "W")
UNITS = ("mm", "mm", "mm", "deg", "deg", "deg")
LOW = (-50.0, -50.0, -25.0, -30.0, -30.0, -30.0)
HIGH = (50.0, 50.0, 25.0, 30.0, 30.0, 30.0)


def _ring(radius: float, centres_deg: tuple[float, ...], half_deg: float, z: float) -> NDArray[np.float64]:
    pts = []
    for c in centres_deg:
        for s in (-1.0, 1.0):
            t = math.radians(c + s * half_deg)
            pts.append([radius * math.cos(t), radius * math.sin(t), z])
    return np.asarray(pts)


# Leg joints in the lab frame at the home pose (origin = nominal isocenter, platform below it).
BASE_JOINTS = _ring(160.0, (0.0, 120.0, 240.0), 10.0, -330.0)
PLATFORM_JOINTS = _ring(110.0, (60.0, 180.0, 300.0), 50.0, -150.0)[[5, 0, 1, 2, 3, 4]]


def leg_lengths(pose_deg: NDArray[np.float64], pivot_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """Lengths (mm) of the six legs for a pose (X, Y, Z mm; U, V, W deg) about a pivot."""
    q = np.concatenate([pose_deg[:3], np.radians(pose_deg[3:])])
    R, t = hexapod_transform(q, pivot_mm)
    return np.linalg.norm(PLATFORM_JOINTS @ R.T + t - BASE_JOINTS, axis=1)


HOME_LEG_MM = float(leg_lengths(np.zeros(6), np.zeros(3))[0])
# +-80 mm of stroke (an H-850-class hexapod): the published orbits (tilts up to 30 deg) and the +-20 deg sawtooth with
# its bench errors (~23 deg, 10 mm) stay reachable,
# while corners such as X = Y = 50 mm with U = V = 30 deg do not.
LEG_RANGE_MM = (HOME_LEG_MM - 80.0, HOME_LEG_MM + 80.0)


class HexapodController(GcsController):
    """C-887-like hexapod controller twin."""

    idn = "(c)2026 Physik Instrumente (PI) GmbH & Co. KG, C-887.52, 126000001, 2.3.0.0"
    reference_pose = (0.0,) * 6
    command_names = GcsController.command_names + ("VLS", "VLS?", "SPI", "SPI?", "VMO?")
    max_velocity = 20.0  # mm/s (and deg/s for U, V, W)

    def __init__(
        self,
        world: SimWorld | None = None,
        *,
        time_scale: float = 1.0,
        imperfect: bool = True,
        seed: int = 7,
        faults: TwinFaults | None = None,
        velocity: float = 10.0,
    ) -> None:
        start = (0.31, -0.22, -1.05, 0.04, -0.03, 0.12)  # where the platform happens to be at power-on
        super().__init__(AXES, UNITS, LOW, HIGH, start, time_scale=time_scale, faults=faults)
        self.world = world
        self.velocity = float(velocity)
        self.pivot = np.asarray(world.pivot_mm if world is not None else (0.0, 0.0, 0.0), dtype=float)
        rng = np.random.default_rng(seed)
        on = 1.0 if imperfect else 0.0
        self.encoder_offset = on * np.concatenate([rng.normal(0, 0.02, 3), rng.normal(0, 0.005, 3)])
        self.backlash = on * np.array([0.004, 0.004, 0.002, 0.002, 0.002, 0.003])
        self.sag_mm = on * 0.012  # Z sag at zero tilt
        self.sag_per_deg_mm = on * 0.0025  # extra Z sag per degree of tilt
        self.tilt_droop = on * 0.002  # U, V fall short by this fraction
        self.noise = on * 5e-5
        self._rng = np.random.default_rng(seed + 1)

    # ----- physics -----
    def speeds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        v = np.full(6, self.velocity)
        return v, 10.0 * v  # reaches speed in 0.1 s

    def reference_speeds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        v = np.full(6, 5.0)
        return v, 10.0 * v

    def movable_mask(self, idx: list[int]) -> NDArray[np.bool_]:
        return np.ones(6, dtype=bool)  # legs are coupled: every axis needs servo and reference

    def reachable(self, pose: NDArray[np.float64]) -> bool:
        """Whether the legs can reach ``pose`` (X, Y, Z mm; U, V, W deg) about the current pivot."""
        legs = leg_lengths(pose, self.pivot)
        return bool(np.all(legs >= LEG_RANGE_MM[0]) and np.all(legs <= LEG_RANGE_MM[1]))

    def within_limits(self, pose: NDArray[np.float64]) -> bool:
        return super().within_limits(pose) and self.reachable(pose)

    def true_pose(self) -> NDArray[np.float64]:
        """The mechanical pose (X, Y, Z mm; U, V, W deg) including the hidden errors."""
        enc = self.motion.position()
        tilt = math.hypot(enc[3], enc[4])
        true = enc + self.encoder_offset - 0.5 * self.backlash * self.motion.last_direction
        true[2] -= self.sag_mm + self.sag_per_deg_mm * tilt
        true[3:5] -= self.tilt_droop * enc[3:5]
        return true

    def readback(self) -> NDArray[np.float64]:
        return self.motion.position() + self._rng.normal(0.0, self.noise, 6) * self.referenced

    def publish(self) -> None:
        if self.world is None:
            return
        true = self.true_pose()
        with self.world.lock:
            self.world.hexapod_true = np.concatenate([true[:3], np.radians(true[3:])])
            self.world.pivot_mm = (float(self.pivot[0]), float(self.pivot[1]), float(self.pivot[2]))

    # ----- hexapod commands -----
    def _vls(self, s: Session, a: list[str]) -> Reply:
        if len(a) != 1:
            raise GcsError(E.PARAM_NR)
        try:
            v = float(a[0])
        except ValueError:
            raise GcsError(E.PARAM_SYNTAX) from None
        if not 0.0 < v <= self.max_velocity:
            raise GcsError(E.PARAM_OUT_OF_RANGE)
        self.velocity = v
        return None

    def _vls_q(self, s: Session, a: list[str]) -> Reply:
        return [self._fmt(self.velocity)]

    def _spi(self, s: Session, a: list[str]) -> Reply:
        if not a or len(a) % 2:
            raise GcsError(E.PARAM_NR)
        names = {"R": 0, "S": 1, "T": 2}
        new = self.pivot.copy()
        for k, v in zip(a[::2], a[1::2]):
            if k.upper() not in names:
                raise GcsError(E.ILLEGAL_AXIS)
            try:
                new[names[k.upper()]] = float(v)
            except ValueError:
                raise GcsError(E.PARAM_SYNTAX) from None
        if self.motion.moving().any():
            raise GcsError(E.NOT_ALLOWED_WHILE_MOVING)
        if np.any(np.abs(self.motion.target[3:]) > 1e-9):
            raise GcsError(E.PIVOT_NOT_POSSIBLE)
        self.pivot = new
        return None

    def _spi_q(self, s: Session, a: list[str]) -> Reply:
        names = ["R", "S", "T"]
        want = [k.upper() for k in a] or names
        if any(k not in names for k in want):
            raise GcsError(E.ILLEGAL_AXIS)
        return [f"{k}={self._fmt(self.pivot[names.index(k)])}" for k in want]

    def _vmo_q(self, s: Session, a: list[str]) -> Reply:
        pose = self.motion.target.copy()
        for i, v in self._pairs(a):
            pose[i] = v
        return ["1" if self.within_limits(pose) else "0"]
