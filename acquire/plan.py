"""What a scan does, frame by frame, as pure data: kind, nominal view, injected error, axis targets.

A plan knows nothing about devices; the engine (``acquire.engine``) runs it.
Darks and flats are taken at the pose of the first (before) or last (after) projection.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from acquire.config import BenchConfig
from acquire.errors import AcquireError
from acquire.kinematics import bench_axes
from orbitct.geometry import Panel, ViewGeometry
from orbitct.scanfile.keys import ImageKey


@dataclass(frozen=True)
class FramePlan:
    """One frame: its index, image key, orbit view (-1 for darks/flats) and axis targets."""

    index: int
    image_key: int
    view: int
    theta_rad: float
    phi_rad: float
    error: NDArray[np.float64]
    stage_rad: float
    hexapod: NDArray[np.float64]
    nominal_vector: NDArray[np.float64]

    @property
    def kind(self) -> str:
        """``projection``, ``flat`` or ``dark``."""
        return ImageKey(self.image_key).label


@dataclass(frozen=True)
class ScanPlan:
    """Every frame of a bench scan (arrays of length N) plus what it came from."""

    image_key: NDArray[np.int8]
    view: NDArray[np.int64]
    theta_rad: NDArray[np.float64]
    phi_rad: NDArray[np.float64]
    errors: NDArray[np.float64]
    stage_rad: NDArray[np.float64]
    hexapod: NDArray[np.float64]
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
            index=i, image_key=int(self.image_key[i]), view=int(self.view[i]),
            theta_rad=float(self.theta_rad[i]), phi_rad=float(self.phi_rad[i]), error=self.errors[i],
            stage_rad=float(self.stage_rad[i]), hexapod=self.hexapod[i], nominal_vector=self.nominal.vectors[i],
        )

    def __iter__(self) -> Iterator[FramePlan]:
        return (self.frame(i) for i in range(self.n_frames))

    def __len__(self) -> int:
        return self.n_frames


def _layout(n_views: int, darks_before: int, flats_before: int, darks_after: int, flats_after: int
            ) -> tuple[NDArray[np.int8], NDArray[np.int64], NDArray[np.int64]]:
    """Image keys, orbit view per frame (-1 for darks/flats) and the view whose pose each frame uses."""
    keys = [ImageKey.DARK] * darks_before + [ImageKey.FLAT] * flats_before + [ImageKey.PROJECTION] * n_views + [ImageKey.DARK] * darks_after + [ImageKey.FLAT] * flats_after
    view = [-1] * (darks_before + flats_before) + list(range(n_views)) + [-1] * (darks_after + flats_after)
    pose = [0] * (darks_before + flats_before) + list(range(n_views)) + [n_views - 1] * (darks_after + flats_after)
    return np.array(keys, np.int8), np.array(view, np.int64), np.array(pose, np.int64)


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
    cf = config.calibration_frames
    keys, view, pose = _layout(th.size, cf.darks_before, cf.flats_before, cf.darks_after, cf.flats_after)
    stage, hexapod = bench_axes(th, ph, err, config.stack)
    proj = keys == ImageKey.PROJECTION
    nominal = np.full((keys.size, 12), np.nan)
    nominal[proj] = config.geometry.carm_views(th, ph).vectors
    return ScanPlan(
        image_key=keys, view=view,
        theta_rad=th[pose], phi_rad=ph[pose], errors=err[pose],
        stage_rad=stage[pose], hexapod=hexapod[pose],
        nominal=ViewGeometry(nominal, config.geometry.detector.panel()),
        orbit_name=orbit_name, orbit_params=dict(orbit_params or {}), error_profile=error_profile,
        config=config.model_dump(mode="json"),
    )
