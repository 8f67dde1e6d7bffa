"""Back-projected rays of detected centroids: distances, pairwise nearest points, triangulation, RPE."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calib.model import all_finite
from orbitct.geometry import ViewGeometry


def marker_rays(geometry: ViewGeometry, uv: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Origins ``(N, K, 3)`` (sources) and unit directions ``(N, K, 3)`` of the rays through centroids ``(N, K, 2)``."""
    origin, direction = geometry.backproject(uv)
    return np.broadcast_to(origin, direction.shape), direction


def point_ray_distance(
    points: NDArray[np.float64], origin: NDArray[np.float64], direction: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance (mm) from points ``(..., 3)`` to rays ``origin + s direction`` (unit directions)."""
    a = points - origin
    along = np.einsum("...i,...i->...", a, direction)
    return np.linalg.norm(a - along[..., None] * direction, axis=-1)


def rpe_per_frame(geometry: ViewGeometry, uv: NDArray[np.float64], xyz: NDArray[np.float64]) -> NDArray[np.float64]:
    """Paper's RPE: per view, mean over its seen markers of the marker-centre-to-ray distance (mm); NaN if none."""
    o, d = marker_rays(geometry, uv)
    dist = point_ray_distance(xyz[None, :, :], o, d)
    seen = np.isfinite(dist)
    with np.errstate(invalid="ignore"):
        return np.where(seen.any(1), np.nansum(dist, 1) / np.maximum(seen.sum(1), 1), np.nan)


def triangulate_least_squares(origin: NDArray[np.float64], direction: NDArray[np.float64]) -> NDArray[np.float64]:
    """Point(s) closest in the least-squares sense to rays ``(N, K, 3)`` per marker k -> ``(K, 3)`` (NaN if < 2 rays)."""
    ok = all_finite(direction) & all_finite(origin)
    d = np.where(ok[..., None], direction, 0.0)
    o = np.where(ok[..., None], origin, 0.0)
    # sums over views of (I - d d^T) and (I - d d^T) o, without the (N, K, 3, 3) stack
    dk = np.ascontiguousarray(d.transpose(1, 2, 0))  # (K, 3, N)
    A = ok.sum(0)[:, None, None] * np.eye(3) - dk @ np.ascontiguousarray(d.transpose(1, 0, 2))
    od = (o * d).sum(-1)  # (N, K)
    b = o.sum(0) - (dk @ od.T[..., None])[..., 0]
    out = np.full((A.shape[0], 3), np.nan)
    good = ok.sum(0) >= 2
    if good.any():
        out[good] = np.linalg.solve(A[good], b[good][..., None])[..., 0]
    return out


def pairwise_midpoint_mean(
    origin: NDArray[np.float64], direction: NDArray[np.float64], chunk: int = 256
) -> NDArray[np.float64]:
    """Paper's BB centre: mean of the midpoints of the common perpendiculars of all ray pairs, per marker -> ``(K, 3)``."""
    n, k = direction.shape[:2]
    out = np.full((k, 3), np.nan)
    for m in range(k):
        ok = all_finite(direction[:, m])
        o, d = origin[ok, m], direction[ok, m]
        if len(o) < 2:
            continue
        total = np.zeros(3)
        count = 0
        for start in range(0, len(o), chunk):
            o1, d1 = o[start : start + chunk, None], d[start : start + chunk, None]
            w = o1 - o[None]
            b = np.einsum("ijk,ijk->ij", d1, d[None].repeat(len(o1), 0))
            dd = np.einsum("ijk,ijk->ij", d1, w)
            e = np.einsum("jk,ijk->ij", d, w)
            den = 1.0 - b**2
            idx = np.arange(start, start + len(o1))
            use = (idx[:, None] < np.arange(len(o))[None, :]) & (den > 1e-12)
            den = np.where(use, den, 1.0)
            s = (b * e - dd) / den
            t = (e - b * dd) / den
            p = 0.5 * ((o1 + s[..., None] * d1) + (o[None] + t[..., None] * d[None]))
            total += (p * use[..., None]).sum((0, 1))
            count += int(use.sum())
        if count:
            out[m] = total / count
    return out
