"""Accuracy of an estimated geometry against a known truth, after the best similarity alignment."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from orbitct.geometry import ViewGeometry
from orbitct.rotations import matrix_to_rotvec, rotvec_to_matrix, similarity_fit


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


def _kabsch(P: NDArray[np.float64], Q: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per set, the rigid motion ``q ~ R p + t`` of point sets ``(N, K, 3)``; returns ``R (N,3,3)``, ``t (N,3)``."""
    pc, qc = P.mean(1), Q.mean(1)
    H = np.einsum("nki,nkj->nij", P - pc[:, None], Q - qc[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    D = np.repeat(np.eye(3)[None], P.shape[0], 0)
    D[:, 2, 2] = d
    R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
    return R, qc - np.einsum("nij,nj->ni", R, pc)


def _assembly_points(g: ViewGeometry) -> NDArray[np.float64]:
    """Source, detector centre and the detector's u and v directions as four points per view ``(N, 4, 3)``."""
    v = g.vectors
    arm = 0.5 * np.linalg.norm(v[:, 0:3] - v[:, 3:6], axis=1, keepdims=True)
    u = v[:, 6:9] / np.linalg.norm(v[:, 6:9], axis=1, keepdims=True)
    w = v[:, 9:12] / np.linalg.norm(v[:, 9:12], axis=1, keepdims=True)
    return np.stack([v[:, 0:3], v[:, 3:6], v[:, 3:6] + arm * u, v[:, 3:6] + arm * w], 1)


def true_corrections(
    estimate: ViewGeometry, nominal: ViewGeometry, truth: ViewGeometry
) -> dict[str, NDArray[np.float64]]:
    """The per-view corrections (``rotvec_rad``, ``shift_mm``, as the calibration reports them) that turn the
    nominal views into the true ones, with the truth first moved into the calibrated frame by the best
    similarity (the calibration fixes its frame by the BBs, not by the truth); NaN where a view has no estimate."""
    n = truth.n_views
    out = {"rotvec_rad": np.full((n, 3), np.nan), "shift_mm": np.full((n, 3), np.nan), "frame": np.arange(n)}
    ok = estimate.valid & truth.valid & nominal.valid
    idx = np.flatnonzero(ok)
    if idx.size < 2:
        return out
    et, tt = estimate[idx], truth[idx]
    s, R, c = similarity_fit(np.concatenate([tt.S, tt.D]), np.concatenate([et.S, et.D]))
    aligned = tt.scaled(s).transformed(R, c)
    Rv, tv = _kabsch(_assembly_points(nominal[idx]), _assembly_points(aligned))
    out["rotvec_rad"][idx] = matrix_to_rotvec(Rv)
    out["shift_mm"][idx] = tv
    return out


def truth_fed_error_px(
    uv: NDArray[np.float64],
    truth: ViewGeometry,
    truth_xyz: NDArray[np.float64],
    nominal: ViewGeometry,
    noise_px: float | None = None,
    seed: int = 0,
) -> tuple[float, float]:
    """What the bundle adjustment reaches from the true projections of the BBs a calibration detected, in the
    views it detected them, plus independent Gaussian noise: the orbit's and placement's own limit, without what
    the object does to the detections. ``uv`` ``(P, K, 2)`` (NaN: not seen), each column taken for the true BB
    (``truth_xyz``) it lies nearest to most often; the noise is ``noise_px`` per axis, by default the detections'
    own RMS error against the truth. Returns the error (RMS px over the FOV, similarity-aligned, over the views
    with at least three BBs) and the detections' own noise."""
    from calib.bundle import bundle_adjust
    from calib.model import ViewModel
    from calib.rays import marker_rays, triangulate_least_squares

    truth_uv = truth.project(truth_xyz)
    d = np.linalg.norm(uv[:, :, None] - truth_uv[:, None], axis=-1)
    seen = np.isfinite(uv[..., 0])
    j = np.nanargmin(np.where(np.isfinite(d), d, np.inf), axis=2)
    diff = (uv - np.take_along_axis(truth_uv, j[..., None].repeat(2, -1), axis=1))[seen]
    own_noise_px = float(np.sqrt(np.mean(diff**2)))
    owner = np.array([np.bincount(j[seen[:, k], k], minlength=truth_uv.shape[1]).argmax() for k in range(uv.shape[1])])
    sigma = own_noise_px if noise_px is None else float(noise_px)
    fed = truth_uv[:, owner] + np.random.default_rng(seed).normal(0.0, sigma, uv.shape)
    fed[~seen] = np.nan
    ok = np.flatnonzero(seen.sum(1) >= 3)
    model = ViewModel(nominal[ok])
    xyz0 = triangulate_least_squares(*marker_rays(model.nominal, fed[ok]))
    result = bundle_adjust(model, fed[ok], xyz0)
    return similarity_aligned_error_px(model.geometry(result.state), truth[ok])[0], own_noise_px


__all__ = ["fov_points", "similarity_aligned_error_px", "true_corrections", "truth_fed_error_px"]
