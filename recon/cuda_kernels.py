"""CUDA kernels (numba-cuda): the Joseph forward projector and its exact adjoint, FDK's filter and voxel-driven
back-projector, and PWLS's residual (the solver's own kernels are in :mod:`recon.cuda_pwls`).

The GPU twins of :mod:`recon.projector`'s CPU kernels, with the same input: per-view rays in voxel-index units
(``recon.operator.index_rays``), a zero-bordered volume, projections ``(views, rows, cols)``, projection matrices on
voxel indices. Every array is passed flat (C order) with its sizes. A ray's set-up is the CPU kernels' own function
(``recon.projector._ray``), compiled for the device, so both walk the same planes with the same float64 positions;
the interpolation and the sums run in float32 as there. The forward projector and the back-projector of FDK give
one thread a ray or a voxel; the adjoint gives one thread a ray and adds its four taps per plane atomically, so it is
the transpose of the forward projector up to the order of float32 additions. FDK's filter gives one block a
detector row.

Imported only when a reconstruction runs on a GPU (:mod:`recon.device`); with ``NUMBA_ENABLE_CUDASIM=1`` numba's
CUDA simulator runs them on the CPU (the tests do, on tiny problems).
"""

from __future__ import annotations

import math

from numba import cuda, float32

from recon.projector import _ray

THREADS = 256  # threads per block of every kernel

_ray_on_device = cuda.jit(device=True)(_ray.py_func)


def blocks(n: int) -> int:
    """Blocks of :data:`THREADS` that cover ``n`` threads."""
    return max(1, (n + THREADS - 1) // THREADS)


def strided_blocks(n: int) -> int:
    """Blocks of a grid-stride kernel over ``n`` elements: enough to fill a GPU, no more than ``n`` needs."""
    return min(1024, blocks(n))


@cuda.jit(device=True)
def _pixel(t, rows, cols):  # type: ignore[no-untyped-def]
    """View, row and column of flat pixel ``t``."""
    per_view = rows * cols
    n = t // per_view
    rc = t - n * per_view
    r = rc // cols
    return n, r, rc - r * cols


@cuda.jit(device=True)
def _tap(a0, ra, b0, rb, k, stm, sta, stb):  # type: ignore[no-untyped-def]
    """Flat index of plane ``k``'s first tap and its two interpolation fractions (as the CPU's ``_taps``)."""
    a = a0 + k * ra
    b = b0 + k * rb
    ia = math.floor(a)
    ib = math.floor(b)
    return int((k + 1.0) * stm + ia * sta + ib * stb), float32(a - ia), float32(b - ib)


@cuda.jit
def forward_kernel(vol, nx, ny, nz, rays, vox, rows, cols, out):  # type: ignore[no-untyped-def]
    """``out[view, row, col]``: the Joseph line integral of the padded ``vol`` along the ray of that pixel."""
    t = cuda.grid(1)
    if t >= rays.shape[0] * rows * cols:
        return
    n, r, c = _pixel(t, rows, cols)
    a0, ra, b0, rb, k_lo, k_hi, step, stm, sta, stb = _ray_on_device(rays, vox, n, r, c, nx, ny, nz)
    acc = float32(0.0)
    for k in range(k_lo, k_hi + 1):
        p, fa, fb = _tap(a0, ra, b0, rb, k, stm, sta, stb)
        v00 = vol[p]
        v01 = vol[p + sta]
        v10 = vol[p + stb]
        v11 = vol[p + sta + stb]
        top = v00 + fa * (v01 - v00)
        bot = v10 + fa * (v11 - v10)
        acc += top + fb * (bot - top)
    out[t] = acc * float32(step)


@cuda.jit
def adjoint_kernel(proj, nx, ny, nz, rays, vox, rows, cols, acc):  # type: ignore[no-untyped-def]
    """Add the transpose of :func:`forward_kernel` applied to ``proj`` into the padded accumulator ``acc``."""
    t = cuda.grid(1)
    if t >= rays.shape[0] * rows * cols:
        return
    val = proj[t]
    if val == 0.0:
        return
    n, r, c = _pixel(t, rows, cols)
    a0, ra, b0, rb, k_lo, k_hi, step, stm, sta, stb = _ray_on_device(rays, vox, n, r, c, nx, ny, nz)
    wv = float32(val * step)
    for k in range(k_lo, k_hi + 1):
        p, fa, fb = _tap(a0, ra, b0, rb, k, stm, sta, stb)
        w1 = fb * wv
        w0 = wv - w1
        w01 = fa * w0
        w11 = fa * w1
        cuda.atomic.add(acc, p, w0 - w01)
        cuda.atomic.add(acc, p + sta, w01)
        cuda.atomic.add(acc, p + stb, w1 - w11)
        cuda.atomic.add(acc, p + sta + stb, w11)


@cuda.jit
def backproject_kernel(img, rows, cols, mats, weights, vol, nx, ny, nz):  # type: ignore[no-untyped-def]
    """Add ``sum_n weights[n] / w^2 * img_n(P_n x)`` into ``vol`` (bilinear, zero outside the panel).

    ``img`` holds the views with a one-pixel zero border, ``(views, rows + 2, cols + 2)``; ``mats`` (views, 3, 4)
    map voxel indices to homogeneous pixels ``(col w, row w, w)``.
    """
    t = cuda.grid(1)
    plane_xy = nx * ny
    if t >= plane_xy * nz:
        return
    z = t // plane_xy
    yx = t - z * plane_xy
    y = yx // nx
    x = yx - y * nx
    cols2 = cols + 2
    per_view = (rows + 2) * cols2
    acc = float32(0.0)
    for n in range(mats.shape[0]):
        wn = weights[n]
        if wn == 0.0:
            continue
        w = mats[n, 2, 0] * x + mats[n, 2, 1] * y + mats[n, 2, 2] * z + mats[n, 2, 3]
        if w <= 0.0:
            continue
        inv = 1.0 / w
        col = (mats[n, 0, 0] * x + mats[n, 0, 1] * y + mats[n, 0, 2] * z + mats[n, 0, 3]) * inv
        row = (mats[n, 1, 0] * x + mats[n, 1, 1] * y + mats[n, 1, 2] * z + mats[n, 1, 3]) * inv
        if not (-1.0 < col < cols and -1.0 < row < rows):
            continue
        col += 1.0  # the padded image's index
        row += 1.0
        ic = int(col)
        ir = int(row)
        fc = float32(col - ic)
        fr = float32(row - ir)
        q = n * per_view + ir * cols2 + ic
        v00 = img[q]
        v01 = img[q + 1]
        v10 = img[q + cols2]
        v11 = img[q + cols2 + 1]
        top = v00 + fc * (v01 - v00)
        bot = v10 + fc * (v11 - v10)
        acc += float32(wn * inv * inv) * (top + fr * (bot - top))
    vol[t] += acc


@cuda.jit
def filter_kernel(proj, rows, cols, coef, parker, use_parker, taps, out):  # type: ignore[no-untyped-def]
    """FDK's filtering, one block per (view, row): the cosine weight (and Parker's), then the ramp filter as a direct
    convolution with its impulse response ``taps`` (circular, of the padded FFT length), into the interior of the
    padded ``out`` ``(views, rows + 2, cols + 2)``. ``coef``: ``recon.fdk.filter_coefficients``. Dynamic shared
    memory holds the row and the taps: ``4 * (cols + len(taps))`` bytes."""
    shared = cuda.shared.array(0, dtype=float32)
    npad = taps.shape[0]
    line = shared[:cols]
    kernel = shared[cols : cols + npad]
    b = cuda.blockIdx.x
    n = b // rows
    r = b - n * rows
    tid = cuda.threadIdx.x
    nt = cuda.blockDim.x
    rr = r - coef[n, 7]
    for c in range(tid, cols, nt):
        cc = c - coef[n, 6]
        dist2 = (
            coef[n, 0]
            + 2.0 * coef[n, 1] * cc
            + 2.0 * coef[n, 2] * rr
            + coef[n, 3] * cc * cc
            + coef[n, 4] * rr * rr
            + 2.0 * coef[n, 5] * cc * rr
        )
        g = proj[b * cols + c] * float32(coef[n, 8] / math.sqrt(dist2))
        if use_parker:
            g *= parker[n * cols + c]
        line[c] = g
    for k in range(tid, npad, nt):
        kernel[k] = taps[k]
    cuda.syncthreads()
    scale = float32(coef[n, 9])
    base = (n * (rows + 2) + r + 1) * (cols + 2) + 1
    for c in range(tid, cols, nt):
        acc = float32(0.0)
        for j in range(c + 1):  # taps 0..c
            acc += line[j] * kernel[c - j]
        for j in range(c + 1, cols):  # negative lags wrap around
            acc += line[j] * kernel[npad + c - j]
        out[base + c] = acc * scale


@cuda.jit
def residual_kernel(ax, y, w, weighted, value):  # type: ignore[no-untyped-def]
    """``ax <- w (ax - y)`` (``w`` = 1 unless ``weighted``), adding ``0.5 sum w (ax - y)^2`` into ``value[0]``."""
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    s = 0.0
    for i in range(start, ax.shape[0], stride):
        d = ax[i] - y[i]
        if weighted:
            ww = w[i]
            s += ww * d * d
            ax[i] = ww * d
        else:
            s += d * d
            ax[i] = d
    cuda.atomic.add(value, 0, 0.5 * s)


@cuda.jit
def scale_kernel(a, w):  # type: ignore[no-untyped-def]
    """``a <- a * w`` element by element."""
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for i in range(start, a.shape[0], stride):
        a[i] *= w[i]


@cuda.jit
def fill_kernel(a, value):  # type: ignore[no-untyped-def]
    """``a <- value``."""
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for i in range(start, a.shape[0], stride):
        a[i] = value
