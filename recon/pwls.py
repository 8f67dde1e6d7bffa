"""PWLS with a quadratic roughness penalty, solved by separable paraboloidal surrogates (SPS).

Cost: ``0.5 * sum_i w_i ([Ax]_i - y_i)^2 + beta_abs * sum_{pairs j~k} omega_jk (x_j - x_k)^2 / 2``.
``beta`` is relative: the penalty curvature of an interior voxel is ``beta`` times the median
data curvature, so one value suits different voxel sizes, view counts and dose levels.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from orbitct.progress import ProgressCallback, report
from recon.errors import ReconError
from recon.operator import Projector

DEFAULT_BETA = 0.01


@dataclass
class PwlsResult:
    """Volume, cost per iteration (index 0 = start) and timing of a PWLS run."""

    volume: NDArray[np.float32]
    cost: list[float] = field(default_factory=list)
    iterations: int = 0
    elapsed_s: float = 0.0
    beta_abs: float = 0.0


def neighbour_offsets(order: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Offsets ``(K, 3)`` (dz, dy, dx) of all neighbours and their weights 1/distance."""
    if order not in (1, 2):
        raise ReconError(f"penalty neighbourhood must be 1 (6 neighbours) or 2 (26 neighbours), got {order}")
    offs = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]
    if order == 1:
        offs = [o for o in offs if sum(map(abs, o)) == 1]
    arr = np.array(offs, dtype=np.int64)
    return arr, 1.0 / np.sqrt((arr**2).sum(1))


@njit(parallel=True, cache=True, fastmath=True)
def penalty_add(x, offs, omega, scale, grad):
    """Add ``scale`` times the roughness gradient into ``grad``; returns the roughness value."""
    nz, ny, nx = x.shape
    total = np.zeros(nz)
    for z in prange(nz):
        acc = 0.0
        for y in range(ny):
            for xx in range(nx):
                xj = x[z, y, xx]
                g = 0.0
                for k in range(offs.shape[0]):
                    zz = z + offs[k, 0]
                    yy = y + offs[k, 1]
                    x2 = xx + offs[k, 2]
                    if zz < 0 or zz >= nz or yy < 0 or yy >= ny or x2 < 0 or x2 >= nx:
                        continue
                    d = xj - x[zz, yy, x2]
                    g += omega[k] * d
                    acc += omega[k] * d * d
                grad[z, y, xx] += scale * g
        total[z] = 0.25 * acc
    return total.sum()


@njit(cache=True, inline="always")
def _curvature(z, y, xx, nz, ny, nx, offs, omega):
    """Separable-surrogate curvature of the penalty: twice the in-volume neighbour weights."""
    c = 0.0
    for k in range(offs.shape[0]):
        zz = z + offs[k, 0]
        yy = y + offs[k, 1]
        x2 = xx + offs[k, 2]
        if 0 <= zz < nz and 0 <= yy < ny and 0 <= x2 < nx:
            c += omega[k]
    return 2.0 * c


@njit(parallel=True, cache=True, fastmath=True, boundscheck=False)
def _residual(ax, y, w, weighted):
    """``ax <- w * (ax - y)`` in place (``w`` = 1 unless ``weighted``); returns ``0.5 * sum w (ax - y)^2``."""
    n = ax.shape[0]
    part = np.zeros(n)
    for i in prange(n):
        s = 0.0
        a = ax[i]
        yy = y[i]
        for r in range(a.shape[0]):
            for c in range(a.shape[1]):
                d = a[r, c] - yy[r, c]
                if weighted:
                    ww = w[i, r, c]
                    s += ww * d * d
                    a[r, c] = ww * d
                else:
                    s += d * d
                    a[r, c] = d
        part[i] = 0.5 * s
    return part.sum()


@njit(parallel=True, cache=True, fastmath=True, boundscheck=False)
def _add_penalty_curvature(denom, beta, offs, omega):
    """``denom += beta * curvature`` of the penalty surrogate, voxel by voxel (once per run)."""
    nz, ny, nx = denom.shape
    for z in prange(nz):
        for y in range(ny):
            for xx in range(nx):
                denom[z, y, xx] += beta * _curvature(z, y, xx, nz, ny, nx, offs, omega)


@njit(parallel=True, cache=True, fastmath=True, boundscheck=False)
def _sps_step(x, grad, denom, scale, nonneg):
    """``x <- [x - scale * grad / denom]_+`` (grad already holds the penalty part; denom its curvature)."""
    nz, ny, nx = x.shape
    for z in prange(nz):
        for y in range(ny):
            for xx in range(nx):
                den = denom[z, y, xx]
                if den <= 0.0:
                    continue
                v = x[z, y, xx] - scale * grad[z, y, xx] / den
                if nonneg and v < 0.0:
                    v = 0.0
                x[z, y, xx] = v


def statistical_weights(raw: NDArray, dark: NDArray, flat: NDArray) -> NDArray[np.float32]:
    """PWLS weights ~ 1/variance of the line integrals: detected counts over mean open-beam counts."""
    open_beam = float(np.mean(np.asarray(flat, dtype=np.float64) - dark))
    if not open_beam > 0:
        raise ReconError("flat field is not brighter than the dark field; cannot form statistical weights")
    return (np.maximum(np.asarray(raw, dtype=np.float32) - dark, 0.0) / open_beam).astype(np.float32)


def pwls_sps(A: Projector, y: NDArray[np.float32], weights: NDArray[np.float32] | None = None, *,
             beta: float = DEFAULT_BETA, iterations: int = 50, x0: NDArray[np.float32] | None = None,
             neighbourhood: int = 1, subsets: int = 1, nonneg: bool = True,
             progress: ProgressCallback | None = None) -> PwlsResult:
    """Minimise the PWLS cost by (ordered-subset) SPS; the cost is monotone without subsets."""
    t0 = time.perf_counter()
    if iterations < 0 or subsets < 1 or beta < 0:
        raise ReconError(f"need iterations >= 0, subsets >= 1, beta >= 0; got {iterations}, {subsets}, {beta}")
    y = np.ascontiguousarray(y, dtype=np.float32)
    if y.shape != A.proj_shape:
        raise ReconError(f"projections: expected shape {A.proj_shape}, got {y.shape}")
    weighted = weights is not None
    w = np.ones((1, 1, 1), np.float32) if weights is None else np.ascontiguousarray(weights, dtype=np.float32)
    if weighted and w.shape != y.shape:
        raise ReconError(f"weights: expected shape {y.shape}, got {w.shape}")
    x = np.zeros(A.vol_shape, np.float32) if x0 is None else np.array(x0, dtype=np.float32, copy=True)
    if nonneg:
        np.maximum(x, 0, out=x)
    offs, omega = neighbour_offsets(neighbourhood)
    # data curvature d = A^T (w * A 1), computed once
    denom = np.ones(A.vol_shape, np.float32)
    tmp = A.forward(denom)
    if weighted:
        tmp *= w
    denom.fill(0.0)
    A.back(tmp, out=denom)
    pos = denom[denom > 0]
    beta_abs = float(beta * (np.median(pos, overwrite_input=True) if pos.size else 0.0) / (2 * omega.sum()))
    del pos
    _add_penalty_curvature(denom, beta_abs, offs, omega)
    n_views = A.proj_shape[0]
    order = [np.arange(m, n_views, subsets) for m in range(subsets)]
    ops = [A] if subsets == 1 else [A.subset(idx) for idx in order]
    cost: list[float] = []
    grad = np.empty(A.vol_shape, np.float32)
    for it in range(iterations + 1):
        data_term = 0.0
        rough = 0.0
        for m, op in enumerate(ops):
            if subsets == 1:
                r = op.forward(x, out=tmp)
                data_term += _residual(r, y, w, weighted)
            else:
                r = op.forward(x)
                data_term += _residual(r, np.ascontiguousarray(y[order[m]]),
                                       np.ascontiguousarray(w[order[m]]) if weighted else w, weighted)
            if it == iterations:
                if m == 0:
                    rough = penalty_add(x, offs, omega, 0.0, grad)
                continue  # final cost only
            grad.fill(0.0)
            op.back(r, out=grad)
            # grad = A_m^T W r + beta/M grad R, so that M * grad is the full-gradient estimate
            rr = penalty_add(x, offs, omega, beta_abs / subsets, grad)
            if m == 0:
                rough = rr
            _sps_step(x, grad, denom, float(subsets), nonneg)
        cost.append(float(data_term + beta_abs * rough))
        if it < iterations:
            el = time.perf_counter() - t0
            report(progress, "pwls", it + 1, iterations, "iterations", cost=cost[-1],
                   time_left_s=el / (it + 1) * (iterations - it - 1))
    return PwlsResult(x, cost, iterations, time.perf_counter() - t0, beta_abs)


