"""What a scan does, frame by frame, as pure data: kind, nominal view, injected error, axis targets.

A plan knows nothing about devices; the engine (``acquire.engine``) runs it on a rig. Axis
targets are keyed as in the scan file's ``/frames/commanded`` (``rotation_stage.R``,
``hexapod.X``, ``carm.primary``) and given in the axis unit (mm or deg). Darks and flats are
taken at the pose of the first (before) or last (after) projection.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from acquire.config import BenchConfig, CalibrationFramesConfig, CArmConfig
from acquire.errors import AcquireError
from acquire.kinematics import HEXAPOD_AXES, HEXAPOD_UNITS, STAGE_AXIS, bench_axes
from orbitct.geometry import Panel, ViewGeometry
from orbitct.orbits import Orbit
from orbitct.scanfile.keys import ImageKey

CARM_AXES = {"carm.primary": "deg", "carm.secondary": "deg"}


@dataclass(frozen=True)
class FramePlan:
    """One frame: its index, image key, orbit view (-1 for darks/flats), injected error and axis targets."""

    index: int
    image_key: int
    view: int
    theta_rad: float
    phi_rad: float
    error: NDArray[np.float64]
    targets: dict[str, float]
    nominal_vector: NDArray[np.float64]

    @property
    def kind(self) -> str:
        """``projection``, ``flat`` or ``dark``."""
        return ImageKey(self.image_key).label


@dataclass(frozen=True)
class ScanPlan:
    """Every frame of a scan (arrays of length N) plus what it came from."""

    image_key: NDArray[np.int8]
    view: NDArray[np.int64]
    theta_rad: NDArray[np.float64]
    phi_rad: NDArray[np.float64]
    errors: NDArray[np.float64]
    targets: Mapping[str, NDArray[np.float64]]
    units: Mapping[str, str]
    nominal: ViewGeometry
    orbit_name: str = ""
    orbit_params: Mapping[str, Any] = field(default_factory=dict)
    error_profile: str = "none"
    config: Mapping[str, Any] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        """Frames in the plan, darks and flats included."""
        return int(self.image_key.shape[0])

    @property
    def n_projections(self) -> int:
        """Projection frames in the plan."""
        return int((self.image_key == ImageKey.PROJECTION).sum())

    @property
    def panel(self) -> Panel:
        """The pixel grid frames are recorded with."""
        return self.nominal.panel

    def frame(self, i: int) -> FramePlan:
        """Frame ``i`` as a record."""
        return FramePlan(
            index=i,
            image_key=int(self.image_key[i]),
            view=int(self.view[i]),
            theta_rad=float(self.theta_rad[i]),
            phi_rad=float(self.phi_rad[i]),
            error=self.errors[i],
            targets={axis: float(values[i]) for axis, values in self.targets.items()},
            nominal_vector=self.nominal.vectors[i],
        )

    def __iter__(self) -> Iterator[FramePlan]:
        return (self.frame(i) for i in range(self.n_frames))

    def __len__(self) -> int:
        return self.n_frames


def frame_layout(
    n_views: int, frames: CalibrationFramesConfig
) -> tuple[NDArray[np.int8], NDArray[np.int64], NDArray[np.int64]]:
    """Image keys, orbit view per frame (-1 for darks/flats) and the view whose pose each frame uses."""
    before, after = frames.darks_before + frames.flats_before, frames.darks_after + frames.flats_after
    keys = (
        [ImageKey.DARK] * frames.darks_before
        + [ImageKey.FLAT] * frames.flats_before
        + [ImageKey.PROJECTION] * n_views
        + [ImageKey.DARK] * frames.darks_after
        + [ImageKey.FLAT] * frames.flats_after
    )
    view = [-1] * before + list(range(n_views)) + [-1] * after
    pose = [0] * before + list(range(n_views)) + [n_views - 1] * after
    return np.array(keys, np.int8), np.array(view, np.int64), np.array(pose, np.int64)


def _nominal(keys: NDArray[np.int8], views: ViewGeometry) -> ViewGeometry:
    vectors = np.full((keys.size, 12), np.nan)
    vectors[keys == ImageKey.PROJECTION] = views.vectors
    return views.with_vectors(vectors)


def plan_bench_scan(
    config: BenchConfig,
    theta_rad: ArrayLike,
    phi_rad: ArrayLike,
    errors: ArrayLike | None = None,
    *,
    orbit_name: str = "",
    orbit_params: Mapping[str, Any] | None = None,
    error_profile: str = "none",
) -> ScanPlan:
    """Plan a bench scan of the nominal views ``(theta, phi)`` with injected errors (N, 6) added."""
    th = np.asarray(theta_rad, dtype=float).ravel()
    ph = np.asarray(phi_rad, dtype=float).ravel()
    if th.shape != ph.shape or th.size == 0:
        raise AcquireError(f"orbit needs matching, non-empty theta and phi arrays, got {th.shape} and {ph.shape}")
    if not (np.isfinite(th).all() and np.isfinite(ph).all()):
        raise AcquireError("orbit angles must be finite")
    err = np.zeros((th.size, 6)) if errors is None else np.asarray(errors, dtype=float)
    if err.shape != (th.size, 6):
        raise AcquireError(f"errors must have shape ({th.size}, 6), got {err.shape}")
    keys, view, pose = frame_layout(th.size, config.calibration_frames)
    stage, hexapod = bench_axes(th, ph, err, config.stack)
    targets = {STAGE_AXIS: np.degrees(stage[pose])}
    for i, axis in enumerate(HEXAPOD_AXES):
        targets[f"hexapod.{axis}"] = hexapod[pose, i] if i < 3 else np.degrees(hexapod[pose, i])
    units = {STAGE_AXIS: "deg"} | {f"hexapod.{a}": u for a, u in zip(HEXAPOD_AXES, HEXAPOD_UNITS)}
    return ScanPlan(
        image_key=keys,
        view=view,
        theta_rad=th[pose],
        phi_rad=ph[pose],
        errors=err[pose],
        targets=targets,
        units=units,
        nominal=_nominal(keys, config.geometry.carm_views(th, ph)),
        orbit_name=orbit_name,
        orbit_params=dict(orbit_params or {}),
        error_profile=error_profile,
        config=config.model_dump(mode="json"),
    )


def plan_carm_scan(config: CArmConfig, orbit: Orbit) -> ScanPlan:
    """Frames of a C-arm scan: darks/flats around the projections, nominal C-arm views, angle targets."""
    keys, view, pose = frame_layout(orbit.n_frames, config.calibration_frames)
    n = keys.size
    targets = {"carm.primary": orbit.theta_deg[pose], "carm.secondary": orbit.phi_deg[pose]}
    return ScanPlan(
        image_key=keys,
        view=view,
        theta_rad=orbit.theta[pose],
        phi_rad=orbit.phi[pose],
        errors=np.zeros((n, 6)),
        targets=targets,
        units=dict(CARM_AXES),
        nominal=_nominal(keys, config.geometry.carm_views(orbit.theta, orbit.phi)),
        orbit_name=orbit.name,
        orbit_params=dict(orbit.params),
        error_profile=json.dumps({"name": "carm-systematic"}),
        config=config.model_dump(mode="json"),
    )


def sweep_end(stage_deg: NDArray[np.float64], start: int, last: int, tol_deg: float = 1e-9) -> int:
    """Last frame of the run from ``start`` in which the sweep axis keeps turning one way (``start`` if it stays)."""
    if start >= last or abs(stage_deg[start + 1] - stage_deg[start]) <= tol_deg:
        return start
    sign = np.sign(stage_deg[start + 1] - stage_deg[start])
    end = start + 1
    while end < last:
        step = stage_deg[end + 1] - stage_deg[end]
        if abs(step) <= tol_deg or np.sign(step) != sign:
            break
        end += 1
    return end


#: how long the sweep axis runs before a sweep's first trigger angle and on past its last one (s), at least
#: :data:`SWEEP_RUN_UP_MIN_DEG`: it is at speed when it passes them
SWEEP_RUN_UP_S = 0.05
SWEEP_RUN_UP_MIN_DEG = 0.01


def sweep_speed(stage_deg: NDArray[np.float64], start: int, end: int, frame_rate_hz: float) -> float:
    """The sweep axis's speed (deg/s) from frame ``start`` to ``end`` of one sweep at ``frame_rate_hz``."""
    return abs(float(stage_deg[end] - stage_deg[start])) / (end - start) * frame_rate_hz


def sweep_run_up_deg(speed_deg_s: float) -> float:
    """How far the sweep axis runs before a sweep's first trigger angle (and on past its last) at ``speed_deg_s``."""
    return max(speed_deg_s * SWEEP_RUN_UP_S, SWEEP_RUN_UP_MIN_DEG)


def sweeps(plan: ScanPlan) -> list[tuple[int, int]]:
    """The first and last frame of every sweep continuous mode makes: a run of projections in which the sweep axis
    (the stage) keeps turning one way."""
    stage = plan.targets[STAGE_AXIS]
    proj = np.flatnonzero(plan.image_key == ImageKey.PROJECTION)
    out: list[tuple[int, int]] = []
    if proj.size == 0:
        return out
    i, last = int(proj[0]), int(proj[-1])
    while i <= last:
        end = sweep_end(stage, i, last)
        if end > i:
            out.append((i, end))
        i = end + 1
    return out


def swept_steps(plan: ScanPlan) -> NDArray[np.bool_]:
    """Per step from frame ``k`` to ``k + 1``: whether continuous mode makes it while the sweep axis (the stage)
    turns at constant speed between two triggers. Steps between sweeps (where the stage stops or turns back, such
    as a rewind after a full turn), to and from darks and flats, and along tilt-only arcs are moves of their own."""
    swept = np.zeros(max(plan.n_frames - 1, 0), dtype=bool)
    for start, end in sweeps(plan):
        swept[start:end] = True
    return swept
