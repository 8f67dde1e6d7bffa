"""Ground-truth attenuation volumes of analytic phantoms, with partial-volume supersampling."""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbitct.phantoms.chords import inside
from orbitct.phantoms.phantom import Phantom
from orbitct.phantoms.primitives import PhantomError

_MAX_THIN_SUPERSAMPLE = 24


@nb.njit(parallel=True, cache=True, nogil=True)
def _add_primitive(
    vol: NDArray[np.float32],
    kind: int,
    M: NDArray[np.float64],
    c: NDArray[np.float64],
    origin: NDArray[np.float64],
    vox: NDArray[np.float64],
    lo: NDArray[np.int64],
    hi: NDArray[np.int64],
    mu: float,
    ss: int,
    thin: bool,
) -> None:
    nz, ny, nx = hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    lat = np.zeros((nz + 1, ny + 1, nx + 1), dtype=np.uint8)
    for a in nb.prange(nz + 1):
        z = origin[2] + (lo[0] + a - 0.5) * vox[2] - c[2]
        for b in range(ny + 1):
            y = origin[1] + (lo[1] + b - 0.5) * vox[1] - c[1]
            for e in range(nx + 1):
                x = origin[0] + (lo[2] + e - 0.5) * vox[0] - c[0]
                y0 = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z
                y1 = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z
                y2 = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z
                lat[a, b, e] = 1 if inside(kind, y0, y1, y2) else 0
    inv = 1.0 / (ss * ss * ss)
    for a in nb.prange(nz):
        for b in range(ny):
            for e in range(nx):
                n = (
                    lat[a, b, e]
                    + lat[a, b, e + 1]
                    + lat[a, b + 1, e]
                    + lat[a, b + 1, e + 1]
                    + lat[a + 1, b, e]
                    + lat[a + 1, b, e + 1]
                    + lat[a + 1, b + 1, e]
                    + lat[a + 1, b + 1, e + 1]
                )
                if n == 8:
                    vol[lo[0] + a, lo[1] + b, lo[2] + e] += mu
                    continue
                if n == 0 and not thin:
                    continue
                cnt = 0
                for qa in range(ss):
                    z = origin[2] + (lo[0] + a - 0.5 + (qa + 0.5) / ss) * vox[2] - c[2]
                    for qb in range(ss):
                        y = origin[1] + (lo[1] + b - 0.5 + (qb + 0.5) / ss) * vox[1] - c[1]
                        for qe in range(ss):
                            x = origin[0] + (lo[2] + e - 0.5 + (qe + 0.5) / ss) * vox[0] - c[0]
                            y0 = M[0, 0] * x + M[0, 1] * y + M[0, 2] * z
                            y1 = M[1, 0] * x + M[1, 1] * y + M[1, 2] * z
                            y2 = M[2, 0] * x + M[2, 1] * y + M[2, 2] * z
                            if inside(kind, y0, y1, y2):
                                cnt += 1
                if cnt:
                    vol[lo[0] + a, lo[1] + b, lo[2] + e] += mu * cnt * inv


@nb.njit(parallel=True, cache=True, nogil=True)
def _add_segment(
    vol: NDArray[np.float32],
    p0: NDArray[np.float64],
    p1: NDArray[np.float64],
    origin: NDArray[np.float64],
    vox: NDArray[np.float64],
    lo: NDArray[np.int64],
    hi: NDArray[np.int64],
    density: float,
) -> None:
    """Add ``density * (length of segment p0-p1 inside the voxel)`` to every voxel of the box ``lo..hi``."""
    d0, d1, d2 = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
    length = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    for a in nb.prange(hi[0] - lo[0] + 1):
        iz = lo[0] + a
        for iy in range(lo[1], hi[1] + 1):
            for ix in range(lo[2], hi[2] + 1):
                t0, t1 = 0.0, 1.0
                for ax, idx, d in ((0, ix, d0), (1, iy, d1), (2, iz, d2)):
                    b0 = origin[ax] + (idx - 0.5) * vox[ax]
                    b1 = b0 + vox[ax]
                    if abs(d) < 1e-300:
                        if p0[ax] < b0 or p0[ax] >= b1:
                            t1 = -1.0
                        continue
                    s0 = (b0 - p0[ax]) / d
                    s1 = (b1 - p0[ax]) / d
                    if s0 > s1:
                        s0, s1 = s1, s0
                    t0 = max(t0, s0)
                    t1 = min(t1, s1)
                if t1 > t0:
                    vol[iz, iy, ix] += density * (t1 - t0) * length


def voxelize(
    phantom: Phantom,
    shape: tuple[int, int, int],
    voxel_mm: float | ArrayLike,
    origin_mm: ArrayLike,
    *,
    supersample: int = 3,
) -> NDArray[np.float32]:
    """Attenuation volume ``(nz, ny, nx)`` float32 (1/mm) on a grid whose voxel ``[0, 0, 0]`` is centred at ``origin_mm``.

    ``voxel_mm`` is one size or ``(x, y, z)`` sizes; voxels cut by a surface get the fraction of
    ``supersample**3`` sub-points inside (exact for voxels wholly inside or outside). Cylinders
    thinner than half a voxel (wires) put their mass along their axis; other primitives thinner
    than a voxel are sampled finer (up to 24 per axis).
    """
    if len(shape) != 3 or min(shape) < 1:
        raise PhantomError(f"shape must be 3 positive sizes (nz, ny, nx), got {shape}")
    vox = np.broadcast_to(np.asarray(voxel_mm, dtype=float), (3,)).copy()
    origin = np.asarray(origin_mm, dtype=float).reshape(3)
    if (vox <= 0).any():
        raise PhantomError(f"voxel_mm must be > 0, got {vox.tolist()}")
    if int(supersample) < 1:
        raise PhantomError(f"supersample must be >= 1, got {supersample}")
    vol = np.zeros(tuple(int(s) for s in shape), dtype=np.float32)
    n_zyx = np.array(vol.shape)
    for p in phantom.primitives:
        cr = p.corners()
        lo_xyz = np.floor((cr.min(0) - origin) / vox) - 1
        hi_xyz = np.ceil((cr.max(0) - origin) / vox) + 1
        lo = np.clip(lo_xyz[::-1], 0, n_zyx - 1).astype(np.int64)
        hi = np.clip(hi_xyz[::-1], -1, n_zyx - 1).astype(np.int64)
        if (hi < lo).any() or (hi_xyz[::-1] < 0).any() or (lo_xyz[::-1] > n_zyx - 1).any():
            continue
        if p.kind == "cylinder" and p.semi_axes[:2].max() < 0.5 * vox.min():
            # a wire: its mass spread along the axis, exact once the cross-section is below a voxel
            axis = p.rotation[:, 2] * p.semi_axes[2]
            density = p.mu * np.pi * p.semi_axes[0] * p.semi_axes[1] / float(np.prod(vox))
            _add_segment(vol, p.center - axis, p.center + axis, origin, vox, lo, hi, density)
            continue
        M = (p.rotation / p.semi_axes).T  # y = diag(1/s) R^T (x - c)
        thin = bool(p.semi_axes.min() < vox.max())
        ss = int(supersample)
        if thin:  # sub-sample spacing finer than the primitive, so thin wires are never missed
            ss = max(ss, min(_MAX_THIN_SUPERSAMPLE, int(np.ceil(3.0 * vox.max() / p.semi_axes.min()))))
        _add_primitive(vol, p.kind_id, np.ascontiguousarray(M), p.center, origin, vox, lo, hi, p.mu, ss, thin)
    return vol
