"""PWLS-SPS with every volume on the GPU: the same algorithm as :func:`recon.pwls.pwls_solve`, step for step.

The iterate, the gradient, the surrogate's denominator and the momentum's last iterate stay on the device as padded
flat float32 arrays; the penalty, the surrogate step and the momentum step are kernels here, their sums reduced per
block. Only the start comes over and the result goes back (and the iterate, when a callback asks for it). The data
term is :class:`recon.cuda.CudaViewsData`. Costs and images equal the CPU solver's to float32 rounding.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import cuda, float64
from numpy.typing import NDArray

from orbitct.progress import ProgressCallback, report
from recon.cuda import CudaViewsData, clear, zeros
from recon.cuda_kernels import THREADS, blocks
from recon.options import DEFAULT_BETA
from recon.pwls_setup import PwlsResult, absolute_beta, checked_start, neighbour_offsets


@cuda.jit(device=True)
def _voxel(t, nx, ny):  # type: ignore[no-untyped-def]
    """Padded flat index and padded (z, y, x) of interior voxel ``t``."""
    x = t % nx
    r = t // nx
    y = r % ny
    z = r // ny
    return ((z + 1) * (ny + 2) + y + 1) * (nx + 2) + x + 1, z + 1, y + 1, x + 1


@cuda.jit(device=True)
def _neighbour(z, y, x, k, offs, nx, ny, nz):  # type: ignore[no-untyped-def]
    """Padded flat index of neighbour ``k`` of the padded voxel (z, y, x); -1 when it lies outside the image."""
    zz = z + offs[k, 0]
    yy = y + offs[k, 1]
    x2 = x + offs[k, 2]
    if zz < 1 or zz > nz or yy < 1 or yy > ny or x2 < 1 or x2 > nx:
        return -1
    return (zz * (ny + 2) + yy) * (nx + 2) + x2


@cuda.jit(device=True)
def _block_sum(shared, v, total):  # type: ignore[no-untyped-def]
    """Add ``v`` of every thread of the block into ``total[0]`` (one atomic add per block). Every thread calls it."""
    tid = cuda.threadIdx.x
    shared[tid] = v
    cuda.syncthreads()
    s = THREADS // 2
    while s > 0:
        if tid < s:
            shared[tid] += shared[tid + s]
        cuda.syncthreads()
        s //= 2
    if tid == 0:
        cuda.atomic.add(total, 0, shared[0])


@cuda.jit
def penalty_kernel(xp, nx, ny, nz, offs, omega, scale, gp, with_gradient, total):  # type: ignore[no-untyped-def]
    """``gp += scale * grad R(x)`` (when ``with_gradient``); adds the roughness ``R`` into ``total[0]``."""
    shared = cuda.shared.array(THREADS, float64)
    t = cuda.grid(1)
    acc = 0.0
    if t < nx * ny * nz:
        p, z, y, x = _voxel(t, nx, ny)
        xj = xp[p]
        g = 0.0
        for k in range(offs.shape[0]):
            q = _neighbour(z, y, x, k, offs, nx, ny, nz)
            if q < 0:
                continue
            d = xj - xp[q]
            g += omega[k] * d
            acc += omega[k] * d * d
        if with_gradient:
            gp[p] += scale * g
    _block_sum(shared, 0.25 * acc, total)


@cuda.jit
def penalty_curvature_kernel(denom, nx, ny, nz, offs, omega, beta):  # type: ignore[no-untyped-def]
    """``denom += beta * (twice the in-volume neighbour weights)``: the penalty's share of the surrogate."""
    t = cuda.grid(1)
    if t >= nx * ny * nz:
        return
    p, z, y, x = _voxel(t, nx, ny)
    c = 0.0
    for k in range(offs.shape[0]):
        if _neighbour(z, y, x, k, offs, nx, ny, nz) >= 0:
            c += omega[k]
    denom[p] += beta * 2.0 * c


@cuda.jit
def sps_kernel(xp, gp, denom, nx, ny, nz, scale, nonneg):  # type: ignore[no-untyped-def]
    """``x <- [x - scale * grad / denom]_+`` voxel by voxel."""
    t = cuda.grid(1)
    if t >= nx * ny * nz:
        return
    p, z, y, x = _voxel(t, nx, ny)
    den = denom[p]
    if den <= 0.0:
        return
    v = xp[p] - scale * gp[p] / den
    if nonneg and v < 0.0:
        v = 0.0
    xp[p] = v


@cuda.jit
def momentum_kernel(zp, gp, denom, nx, ny, nz, scale, nonneg, x_prev, gamma, total):  # type: ignore[no-untyped-def]
    """One OS-momentum step (``recon.pwls._momentum_step``); adds ``sum grad * (x - x_prev_old)`` into ``total``."""
    shared = cuda.shared.array(THREADS, float64)
    t = cuda.grid(1)
    acc = 0.0
    if t < nx * ny * nz:
        p, z, y, x = _voxel(t, nx, ny)
        den = denom[p]
        zv = zp[p]
        v = zv if den <= 0.0 else zv - scale * gp[p] / den
        if nonneg and v < 0.0:
            v = 0.0
        old = x_prev[p]
        acc = gp[p] * (v - old)
        zp[p] = v + gamma * (v - old)
        x_prev[p] = v
    _block_sum(shared, acc, total)


@cuda.jit
def clamp_kernel(a):  # type: ignore[no-untyped-def]
    """``a <- max(a, 0)``."""
    start = cuda.grid(1)
    for i in range(start, a.shape[0], cuda.gridsize(1)):
        if a[i] < 0.0:
            a[i] = 0.0


def _padded(interior: NDArray[np.float32]) -> NDArray[np.float32]:
    out = np.zeros(tuple(n + 2 for n in interior.shape), np.float32)
    out[1:-1, 1:-1, 1:-1] = interior
    return out


def pwls_solve_on_gpu(
    data: CudaViewsData,
    *,
    beta: float = DEFAULT_BETA,
    iterations: int = 50,
    x0: NDArray[np.float32] | None = None,
    neighbourhood: int = 1,
    nonneg: bool = True,
    momentum: bool = False,
    final_cost: bool = False,
    data_curvature: NDArray[np.float32] | None = None,
    keep_data_curvature: Callable[[NDArray[np.float32]], None] | None = None,
    progress: ProgressCallback | None = None,
    callback: Callable[[int, NDArray[np.float32]], None] | None = None,
) -> PwlsResult:
    """:func:`recon.pwls.pwls_solve` with its volumes on the GPU (same arguments, same result)."""
    t0 = time.perf_counter()
    padded = tuple(data.padded_shape)
    given_padded = checked_start(padded, x0, iterations, beta, data_curvature)
    nz, ny, nx = (n - 2 for n in padded)
    n_vox = nx * ny * nz
    size = math.prod(padded)
    volumes = 4 if momentum else 3  # iterate, gradient, denominator (and the last iterate)
    data.check_fits(volumes)
    offs, omega = neighbour_offsets(neighbourhood)
    d_offs, d_omega = cuda.to_device(offs), cuda.to_device(omega)
    if data_curvature is not None:
        denom_host = data_curvature
        d_denom = cuda.to_device(_padded(data_curvature).reshape(-1))
    else:
        d_denom = zeros(size)
        data.curvature_on_device(d_denom)
        denom_host = d_denom.copy_to_host().reshape(padded)[1:-1, 1:-1, 1:-1]
        if keep_data_curvature is not None:
            keep_data_curvature(denom_host)
    beta_abs = absolute_beta(denom_host, beta, omega)
    del denom_host
    grid = (blocks(n_vox), THREADS)
    penalty_curvature_kernel[grid](d_denom, nx, ny, nz, d_offs, d_omega, beta_abs)
    start = (
        given_padded if given_padded is not None else _padded(x0) if x0 is not None else np.zeros(padded, np.float32)
    )
    start = start.copy()  # the border of a padded start is not part of the image
    start[[0, -1]] = 0.0
    start[:, [0, -1]] = 0.0
    start[:, :, [0, -1]] = 0.0
    d_xp = cuda.to_device(start.reshape(-1))
    if nonneg:
        clamp_kernel[min(1024, blocks(size)), THREADS](d_xp)
    d_prev = None  # with momentum: the last iterate (xp holds the extrapolated point)
    if momentum:
        d_prev = cuda.device_array_like(d_xp)
        d_prev.copy_to_device(d_xp)
    d_gp = zeros(size)
    total = cuda.device_array(1, np.float64)
    data.hold(volumes)

    def summed(kernel: Any, *args: Any) -> float:
        total.copy_to_device(np.zeros(1))
        kernel[grid](*args, total)
        return float(total.copy_to_host()[0])

    t_k, restarts = 1.0, 0
    cost: list[float] = []
    subsets = data.subsets
    for it in range(iterations + (1 if final_cost else 0)):
        final = it == iterations
        if final and d_prev is not None:
            d_xp.copy_to_device(d_prev)  # the result is the iterate, not the extrapolated point
        data_term = 0.0
        rough = 0.0
        for m in range(subsets):
            if not final:
                clear(d_gp)
            data_term += data.gradient_on_device(d_xp, m, None if final else d_gp)
            if final:
                if m == 0:
                    rough = summed(penalty_kernel, d_xp, nx, ny, nz, d_offs, d_omega, 0.0, d_gp, False)
                continue
            rr = summed(penalty_kernel, d_xp, nx, ny, nz, d_offs, d_omega, beta_abs / subsets, d_gp, True)
            if m == 0:
                rough = rr
            if d_prev is None:
                sps_kernel[grid](d_xp, d_gp, d_denom, nx, ny, nz, float(subsets), nonneg)
                continue
            t_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t_k * t_k))
            gamma = (t_k - 1.0) / t_next
            args = (d_xp, d_gp, d_denom, nx, ny, nz, float(subsets), nonneg, d_prev, gamma)
            if summed(momentum_kernel, *args) > 0.0:
                d_xp.copy_to_device(d_prev)  # overshot: restart the momentum from the iterate
                t_next, restarts = 1.0, restarts + 1
            t_k = t_next
        cost.append(float(data_term + beta_abs * rough))
        if callback is not None and not final:
            image = (d_xp if d_prev is None else d_prev).copy_to_host().reshape(padded)
            callback(it + 1, image[1:-1, 1:-1, 1:-1])
        if it < iterations:
            el = time.perf_counter() - t0
            report(
                progress,
                "pwls",
                it + 1,
                iterations,
                "iterations",
                cost=cost[-1],
                time_left_s=el / (it + 1) * (iterations - it - 1),
            )
    if d_prev is not None and not final_cost:
        d_xp.copy_to_device(d_prev)
    result = d_xp.copy_to_host().reshape(padded)
    if given_padded is not None:
        given_padded[...] = result
        x = given_padded[1:-1, 1:-1, 1:-1]
    else:
        x = np.ascontiguousarray(result[1:-1, 1:-1, 1:-1])
    return PwlsResult(x, cost, final_cost, iterations, time.perf_counter() - t0, beta_abs, restarts)
