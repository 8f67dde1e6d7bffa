"""Accuracy of an estimated geometry against a known truth, after the best similarity alignment."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from orbitct.geometry import ViewGeometry
from orbitct.rotations import rotvec_to_matrix, similarity_fit


def fov_points(geometry: ViewGeometry, n_per_axis: int = 5, fill: float = 0.8) -> NDArray[np.float64]:
    """A grid of object points filling the field of view seen by every view (cylinder about z)."""
    det = geometry.panel
    ok = geometry.valid
    mag = np.median(geometry.sdd[ok] / geometry.sod()[ok])
    radius = fill * 0.5 * det.cols * det.pitch_col / mag
    half_height = fill * 0.5 * det.rows * det.pitch_row / mag
    s = np.linspace(-1.0, 1.0, n_per_axis)
    x, y, z = np.meshgrid(s, s, s, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    pts = pts[(pts[:, 0] ** 2 + pts[:, 1] ** 2) <= 1.0 + 1e-9]
    return pts * np.array([radius, radius, half_height])


def similarity_aligned_error_px(
    estimate: ViewGeometry, truth: ViewGeometry, points: NDArray[np.float64] | None = None, max_views: int = 300
) -> tuple[float, NDArray[np.float64]]:
    """RMS pixel difference between projecting truth-frame points through the truth and their best
    similarity image through the estimate; also the per-view RMS ``(N,)`` (NaN where either is NaN)."""
    ok = estimate.valid & truth.valid
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return float("nan"), np.full(truth.n_views, np.nan)
    pts = fov_points(truth[idx]) if points is None else points
    sub = idx[np.linspace(0, idx.size - 1, min(max_views, idx.size)).astype(int)]
    et, tt = estimate[sub], truth[sub]
    ref = tt.project(pts)
    src = np.concatenate([tt.S, tt.D])
    dst = np.concatenate([et.S, et.D])
    s0, R0, c0 = similarity_fit(src, dst)

    def unpack(x: NDArray[np.float64]) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
        return s0 * np.exp(x[6]), rotvec_to_matrix(x[0:3]) @ R0, c0 + x[3:6]

    def resid(x: NDArray[np.float64]) -> NDArray[np.float64]:
        s, R, c = unpack(x)
        return (et.project(s * pts @ R.T + c) - ref).ravel()

    x = least_squares(resid, np.zeros(7), x_scale=np.array([1e-3] * 3 + [1.0] * 3 + [1e-3])).x
    s, R, c = unpack(x)
    diff = estimate[idx].project(s * pts @ R.T + c) - truth[idx].project(pts)
    per_view = np.full(truth.n_views, np.nan)
    per_view[idx] = np.sqrt((diff**2).sum(-1).mean(-1))
    return float(np.sqrt((diff**2).sum(-1).mean())), per_view


__all__ = ["fov_points", "similarity_aligned_error_px"]
