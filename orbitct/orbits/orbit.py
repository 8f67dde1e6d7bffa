"""The :class:`Orbit` value: a named, parameterised sequence of nominal views."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import Panel, ViewGeometry, ideal_bench_pose


def _frozen(a: Any) -> NDArray[np.float64]:
    arr = np.array(a, dtype=float).reshape(-1)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Orbit:
    """Nominal rotation ``theta`` and tilt ``phi`` (rad) per frame, with the parameters that made them."""

    name: str
    params: dict[str, Any]
    theta: NDArray[np.float64]
    phi: NDArray[np.float64]
    segment: NDArray[np.int64] = field(default=None)  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        th, ph = _frozen(self.theta), _frozen(self.phi)
        if th.shape != ph.shape:
            raise ValueError(f"theta and phi must have the same length, got {th.shape} and {ph.shape}")
        seg = np.zeros(th.shape, dtype=np.int64) if self.segment is None else np.asarray(self.segment, np.int64)
        if seg.shape != th.shape:
            raise ValueError(f"segment must have one entry per frame, got {seg.shape} for {th.shape[0]} frames")
        seg = seg.copy()
        seg.setflags(write=False)
        object.__setattr__(self, "theta", th)
        object.__setattr__(self, "phi", ph)
        object.__setattr__(self, "segment", seg)
        object.__setattr__(self, "params", dict(self.params))

    @property
    def n_frames(self) -> int:
        """Number of projection frames."""
        return int(self.theta.shape[0])

    @property
    def theta_deg(self) -> NDArray[np.float64]:
        """Rotation angle per frame in degrees."""
        return np.degrees(self.theta)

    @property
    def phi_deg(self) -> NDArray[np.float64]:
        """Tilt angle per frame in degrees."""
        return np.degrees(self.phi)

    @property
    def n_segments(self) -> int:
        """Number of separately driven parts (arcs, circles)."""
        return int(self.segment.max()) + 1 if self.n_frames else 0

    def step_sizes(self) -> tuple[float, float]:
        """Mean per-frame step (rad) of rotation and tilt over frames where that axis moves."""
        out = []
        same = self.segment[1:] == self.segment[:-1]
        for a in (self.theta, self.phi):
            d = np.abs(np.diff(a))[same]
            moving = d > 1e-12
            out.append(float(d[moving].mean()) if moving.any() else 0.0)
        return out[0], out[1]

    def poses(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Ideal bench object poses ``(R (N,3,3), t (N,3))`` that realise the nominal views."""
        return ideal_bench_pose(self.theta, self.phi), np.zeros((self.n_frames, 3))

    def nominal_geometry(self, sad_mm: float, sdd_mm: float, detector: Panel) -> ViewGeometry:
        """Nominal views of this orbit for a source/detector at the given distances."""
        return ViewGeometry.from_carm(self.theta, self.phi, sad_mm, sdd_mm, detector)

    def to_json(self) -> dict[str, Any]:
        """``{'name': ..., 'params': ...}``; :func:`orbitct.orbits.make_orbit` rebuilds it."""
        return {"name": self.name, "params": dict(self.params)}

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        if not self.n_frames:
            return f"Orbit({self.name!r}, 0 frames)"
        return (
            f"Orbit({self.name!r}, {self.n_frames} frames, {self.n_segments} segment(s), "
            f"rotation {self.theta_deg.min():.1f}..{self.theta_deg.max():.1f} deg, "
            f"tilt {self.phi_deg.min():.1f}..{self.phi_deg.max():.1f} deg)"
        )
