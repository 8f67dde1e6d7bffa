"""Compiled CPU kernels: Joseph forward projector, its exact adjoint, voxel-driven FDK back-projector.

Geometry enters as per-view rays in voxel-index coordinates (x, y, z order, index units):
source ``s``, the point of pixel (0, 0) ``p00``, and the column/row steps ``du``, ``dv``.
Volumes are C-ordered ``(nz, ny, nx)`` float32; projections ``(views, rows, cols)`` float32.
Rays running mostly along x use a transposed copy ``(nz, nx, ny)`` so that their bilinear
reads and writes stay contiguous.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _ray(rays, vox, n, r, c, nx, ny, nz):
    """Joseph set-up of one ray: main axis, plane range and the linear map plane -> (a, b)."""
    sx, sy, sz = rays[n, 0], rays[n, 1], rays[n, 2]
    dx = rays[n, 3] + c * rays[n, 6] + r * rays[n, 9] - sx
    dy = rays[n, 4] + c * rays[n, 7] + r * rays[n, 10] - sy
    dz = rays[n, 5] + c * rays[n, 8] + r * rays[n, 11] - sz
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    length = math.sqrt((dx * vox[0]) ** 2 + (dy * vox[1]) ** 2 + (dz * vox[2]) ** 2)
    if ax >= ay and ax >= az:  # x-main rays read the transposed copy (nz, nx, ny): y is contiguous
        m, dm, sm, nm = 0, dx, sx, nx
        da, sa, na, sta = dy, sy, ny, 1
        db, sb, nb, stb = dz, sz, nz, nx * ny
        stm = ny
    elif ay >= az:
        m, dm, sm, nm = 1, dy, sy, ny
        da, sa, na, sta = dx, sx, nx, 1
        db, sb, nb, stb = dz, sz, nz, nx * ny
        stm = nx
    else:
        m, dm, sm, nm = 2, dz, sz, nz
        da, sa, na, sta = dx, sx, nx, 1
        db, sb, nb, stb = dy, sy, ny, nx
        stm = nx * ny
    ra = da / dm
    rb = db / dm
    a0 = sa - sm * ra
    b0 = sb - sm * rb
    step = length / abs(dm)
    lo = 0.0
    hi = nm - 1.0
    # keep planes where -1 < a < na and -1 < b < nb (zero padding beyond)
    if ra != 0.0:
        t1 = (-1.0 - a0) / ra
        t2 = (na - a0) / ra
        lo = max(lo, min(t1, t2))
        hi = min(hi, max(t1, t2))
    elif not (-1.0 < a0 < na):
        hi = -1.0
    if rb != 0.0:
        t1 = (-1.0 - b0) / rb
        t2 = (nb - b0) / rb
        lo = max(lo, min(t1, t2))
        hi = min(hi, max(t1, t2))
    elif not (-1.0 < b0 < nb):
        hi = -1.0
    k_lo = int(math.ceil(lo))
    k_hi = int(math.floor(hi))
    return m, a0, ra, b0, rb, k_lo, k_hi, step, stm, sta, stb, na, nb


@njit(cache=True, inline="always")
def _cell(a0, ra, b0, rb, k):
    """Interpolation cell and fractions of plane ``k`` (shared so forward and adjoint weights are identical)."""
    a = a0 + k * ra
    b = b0 + k * rb
    ia = int(math.floor(a))
    ib = int(math.floor(b))
    return ia, ib, a - ia, b - ib


@njit(cache=True, inline="always")
def _inside(a0, ra, lo, hi, k_lo, k_hi):
    """Planes ``[s, e]`` within ``[k_lo, k_hi]`` where ``lo <= a0 + k ra < hi`` (one plane of margin each side)."""
    if ra == 0.0:
        if lo <= a0 < hi:
            return k_lo, k_hi
        return k_lo, k_lo - 1
    t1 = (lo - a0) / ra
    t2 = (hi - a0) / ra
    s = int(math.ceil(min(t1, t2))) + 1
    e = int(math.floor(max(t1, t2))) - 1
    return max(s, k_lo), min(e, k_hi)


@njit(cache=True, inline="always")
def _sample_checked(flat, base, ia, ib, fa, fb, sta, stb, na, nb):
    acc = 0.0
    if ib >= 0:
        if ia >= 0:
            acc += (1.0 - fa) * (1.0 - fb) * flat[base + ia * sta + ib * stb]
        if ia + 1 < na:
            acc += fa * (1.0 - fb) * flat[base + (ia + 1) * sta + ib * stb]
    if ib + 1 < nb:
        if ia >= 0:
            acc += (1.0 - fa) * fb * flat[base + ia * sta + (ib + 1) * stb]
        if ia + 1 < na:
            acc += fa * fb * flat[base + (ia + 1) * sta + (ib + 1) * stb]
    return acc


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def joseph_forward(vol, vol_t, rays, vox, out):
    """Line integrals of ``vol`` (and its transpose ``vol_t``) along every ray into ``out`` (views, rows, cols)."""
    nz, ny, nx = vol.shape
    nv, rows, cols = out.shape
    flat_n = vol.ravel()
    flat_t = vol_t.ravel()
    for job in prange(nv * rows):
        n = job // rows
        r = job - n * rows
        for c in range(cols):
            m, a0, ra, b0, rb, k_lo, k_hi, step, stm, sta, stb, na, nb = _ray(rays, vox, n, r, c, nx, ny, nz)
            flat = flat_t if m == 0 else flat_n
            # interior planes need no bounds checks; the few planes at the edges do
            s_a, e_a = _inside(a0, ra, 0.0, na - 1.0, k_lo, k_hi)
            s_i, e_i = _inside(b0, rb, 0.0, nb - 1.0, s_a, e_a)
            if e_i < s_i:
                s_i, e_i = k_hi + 1, k_hi
            acc = 0.0
            for k in range(k_lo, min(s_i, k_hi + 1)):
                ia, ib, fa, fb = _cell(a0, ra, b0, rb, k)
                acc += _sample_checked(flat, k * stm, ia, ib, fa, fb, sta, stb, na, nb)
            for k in range(s_i, e_i + 1):
                ia, ib, fa, fb = _cell(a0, ra, b0, rb, k)
                p = k * stm + ia * sta + ib * stb
                top = flat[p] + fa * (flat[p + sta] - flat[p])
                bot = flat[p + stb] + fa * (flat[p + sta + stb] - flat[p + stb])
                acc += top + fb * (bot - top)
            for k in range(max(e_i + 1, k_lo), k_hi + 1):
                ia, ib, fa, fb = _cell(a0, ra, b0, rb, k)
                acc += _sample_checked(flat, k * stm, ia, ib, fa, fb, sta, stb, na, nb)
            out[n, r, c] = acc * step


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def joseph_adjoint(proj, rays, vox, vol, vol_t, n_slabs):
    """Add the exact transpose of :func:`joseph_forward` applied to ``proj`` into ``vol`` and ``vol_t``.

    The caller adds the transpose of ``vol_t`` (x-main rays) to ``vol``. Race-free: each
    parallel task owns a slab of z slices and writes only there.
    """
    nz, ny, nx = vol.shape
    nv, rows, cols = proj.shape
    flat_n = vol.ravel()
    flat_t = vol_t.ravel()
    for sl in prange(n_slabs):
        z0 = sl * nz // n_slabs
        z1 = (sl + 1) * nz // n_slabs
        if z1 <= z0:
            continue
        for n in range(nv):
            for r in range(rows):
                for c in range(cols):
                    val = proj[n, r, c]
                    if val == 0.0:
                        continue
                    m, a0, ra, b0, rb, k_lo, k_hi, step, stm, sta, stb, na, nb = _ray(rays, vox, n, r, c, nx, ny, nz)
                    if k_hi < k_lo:
                        continue
                    flat = flat_t if m == 0 else flat_n
                    if m == 2:  # planes are z slices
                        k_lo = max(k_lo, z0)
                        k_hi = min(k_hi, z1 - 1)
                    else:  # b is z: keep planes with z0 - 1 <= b < z1
                        if rb != 0.0:
                            t1 = (z0 - 1.0 - b0) / rb
                            t2 = (z1 - b0) / rb
                            k_lo = max(k_lo, int(math.floor(min(t1, t2))) - 1)
                            k_hi = min(k_hi, int(math.ceil(max(t1, t2))) + 1)
                        elif not (z0 - 1.0 <= b0 < z1):
                            continue
                    wv = val * step
                    # interior planes: all four corners in the volume and (b along z) in this slab
                    b_lo = 0.0 if m == 2 else max(0.0, z0 * 1.0)
                    b_hi = nb - 1.0 if m == 2 else min(nb - 1.0, z1 - 1.0)
                    s_a, e_a = _inside(a0, ra, 0.0, na - 1.0, k_lo, k_hi)
                    s_i, e_i = _inside(b0, rb, b_lo, b_hi, s_a, e_a)
                    if e_i < s_i:
                        s_i, e_i = k_hi + 1, k_hi
                    for k in range(s_i, e_i + 1):
                        ia, ib, fa, fb = _cell(a0, ra, b0, rb, k)
                        p = k * stm + ia * sta + ib * stb
                        flat[p] += (1.0 - fa) * (1.0 - fb) * wv
                        flat[p + sta] += fa * (1.0 - fb) * wv
                        flat[p + stb] += (1.0 - fa) * fb * wv
                        flat[p + sta + stb] += fa * fb * wv
                    for k in range(k_lo, k_hi + 1):
                        if s_i <= k <= e_i:
                            continue
                        ia, ib, fa, fb = _cell(a0, ra, b0, rb, k)
                        base = k * stm
                        if m == 2:
                            lo_ok = ib >= 0
                            hi_ok = ib + 1 < nb
                        else:
                            lo_ok = z0 <= ib < z1
                            hi_ok = z0 <= ib + 1 < z1
                        if lo_ok:
                            if ia >= 0:
                                flat[base + ia * sta + ib * stb] += (1.0 - fa) * (1.0 - fb) * wv
                            if ia + 1 < na:
                                flat[base + (ia + 1) * sta + ib * stb] += fa * (1.0 - fb) * wv
                        if hi_ok:
                            if ia >= 0:
                                flat[base + ia * sta + (ib + 1) * stb] += (1.0 - fa) * fb * wv
                            if ia + 1 < na:
                                flat[base + (ia + 1) * sta + (ib + 1) * stb] += fa * fb * wv


@njit(cache=True, inline="always")
def _half(a, b, lo, hi):
    """Restrict the open interval ``(lo, hi)`` to where ``a x + b > 0``."""
    if a > 0.0:
        lo = max(lo, -b / a)
    elif a < 0.0:
        hi = min(hi, -b / a)
    elif b <= 0.0:
        hi = lo
    return lo, hi


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def voxel_backproject(proj_padded, mats, weights, vol):
    """Add ``sum_n weights[n] / w^2 * proj_n(P_n x)`` (bilinear, zero outside) into ``vol``.

    ``proj_padded`` (views, rows + 2, cols + 2) carries a one-pixel zero border; ``mats``
    (views, 3, 4) map voxel indices (x, y, z, 1) to homogeneous pixels (col w, row w, w).
    """
    nz, ny, nx = vol.shape
    nv, rows2, cols2 = proj_padded.shape
    rows = rows2 - 2
    cols = cols2 - 2
    for zy in prange(nz * ny):
        z = zy // ny
        y = zy - z * ny
        line = np.zeros(nx, dtype=np.float32)
        for n in range(nv):
            wn = weights[n]
            if wn == 0.0:
                continue
            p = mats[n]
            img = proj_padded[n]
            cu = p[0, 1] * y + p[0, 2] * z + p[0, 3]
            cv = p[1, 1] * y + p[1, 2] * z + p[1, 3]
            cw = p[2, 1] * y + p[2, 2] * z + p[2, 3]
            pu = p[0, 0]
            pv = p[1, 0]
            pw = p[2, 0]
            # voxels of this row that land on the detector: five linear conditions on x
            lo, hi = -1.0, nx * 1.0
            lo, hi = _half(pw, cw, lo, hi)
            lo, hi = _half(pu + pw, cu + cw, lo, hi)
            lo, hi = _half(cols * pw - pu, cols * cw - cu, lo, hi)
            lo, hi = _half(pv + pw, cv + cw, lo, hi)
            lo, hi = _half(rows * pw - pv, rows * cw - cv, lo, hi)
            x0 = max(int(math.floor(lo)) + 1, 0)
            x1 = min(int(math.ceil(hi)) - 1, nx - 1)
            for x in range(x0, x1 + 1):
                inv = 1.0 / (cw + pw * x)
                col = min(max((cu + pu * x) * inv + 1.0, 0.0), cols + 0.999)
                row = min(max((cv + pv * x) * inv + 1.0, 0.0), rows + 0.999)
                ic = int(col)
                ir = int(row)
                fc = col - ic
                fr = row - ir
                top = img[ir, ic] + fc * (img[ir, ic + 1] - img[ir, ic])
                bot = img[ir + 1, ic] + fc * (img[ir + 1, ic + 1] - img[ir + 1, ic])
                line[x] += wn * inv * inv * (top + fr * (bot - top))
        for x in range(nx):
            vol[z, y, x] += line[x]
