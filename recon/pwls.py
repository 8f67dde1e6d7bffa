"""PWLS with a quadratic roughness penalty, solved by separable paraboloidal surrogates (SPS).

Cost: ``0.5 * sum_i w_i ([Ax]_i - y_i)^2 + beta_abs * sum_{pairs j~k} omega_jk (x_j - x_k)^2 / 2``.
``beta`` is relative: the penalty curvature of an interior voxel is ``beta`` times the median
data curvature, so one value suits different voxel sizes, view counts and dose levels.

``momentum=True`` combines the ordered subsets with Nesterov's momentum (OS-SQS-mom, Kim, Ramani and
Fessler, IEEE TMI 2015): each subset step starts from an extrapolation of the last two iterates. Safeguard:
the momentum restarts (O'Donoghue and Candes, 2015) whenever a step's gradient points against the
direction the iterates moved, the sign that the extrapolation overshot; the cost then cannot run away.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from orbitct.progress import ProgressCallback, report
from recon.errors import ReconError
from recon.fdk import ProjectionStack
from recon.operator import Projector
from recon.options import DEFAULT_BETA
from recon.pwls_setup import (
    PwlsResult,
    absolute_beta,
    checked_start,
    neighbour_offsets,
    ordered_subsets,
    subset_operator,
    view_rows,
)


@njit(parallel=True, cache=True, fastmath=True, boundscheck=False)
def penalty_add(
    xp: NDArray[np.floating[Any]],
    offs: NDArray[np.integer[Any]],
    omega: NDArray[np.floating[Any]],
    scale: float,
    gp: NDArray[np.floating[Any]],
) -> float:
    """Add ``scale`` times the roughness gradient into the padded ``gp``; returns the roughness of padded ``xp``.

    Both volumes carry a one-voxel border that is not part of the image: neighbours there are absent.
    """
    nz = xp.shape[0] - 2
    ny = xp.shape[1] - 2
    nx = xp.shape[2] - 2
    total = np.zeros(nz)
    for z in prange(1, nz + 1):
        acc = 0.0
        for y in range(1, ny + 1):
            for xx in range(1, nx + 1):
                xj = xp[z, y, xx]
                g = 0.0
                for k in range(offs.shape[0]):
                    zz = z + offs[k, 0]
                    yy = y + offs[k, 1]
                    x2 = xx + offs[k, 2]
                    if zz < 1 or zz > nz or yy < 1 or yy > ny or x2 < 1 or x2 > nx:
                        continue
                    d = xj - xp[zz, yy, x2]
                    g += omega[k] * d
                    acc += omega[k] * d * d
                gp[z, y, xx] += scale * g
        total[z - 1] = 0.25 * acc
    return total.sum()


@njit(cache=True, inline="always")
def _curvature(
    z: int, y: int, xx: int, nz: int, ny: int, nx: int, offs: NDArray[np.integer[Any]], omega: NDArray[np.floating[Any]]
) -> float:
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
def _residual(
    ax: NDArray[np.floating[Any]], y: NDArray[np.floating[Any]], w: NDArray[np.floating[Any]], weighted: bool
) -> float:
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
def _add_penalty_curvature(
    denom: NDArray[np.floating[Any]], beta: float, offs: NDArray[np.integer[Any]], omega: NDArray[np.floating[Any]]
) -> None:
    """``denom += beta * curvature`` of the penalty surrogate, voxel by voxel (once per run)."""
    nz, ny, nx = denom.shape
    for z in prange(nz):
        for y in range(ny):
            for xx in range(nx):
                denom[z, y, xx] += beta * _curvature(z, y, xx, nz, ny, nx, offs, omega)


@njit(parallel=True, cache=True, fastmath=True, boundscheck=False)
def _sps_step(
    xp: NDArray[np.floating[Any]],
    gp: NDArray[np.floating[Any]],
    denom: NDArray[np.floating[Any]],
    scale: float,
    nonneg: bool,
) -> None:
    """``x <- [x - scale * grad / denom]_+`` on the interior of padded ``xp`` (``gp`` padded, ``denom`` not)."""
    nz, ny, nx = denom.shape
    for z in prange(nz):
        for y in range(ny):
            for xx in range(nx):
                den = denom[z, y, xx]
                if den <= 0.0:
                    continue
                v = xp[z + 1, y + 1, xx + 1] - scale * gp[z + 1, y + 1, xx + 1] / den
                if nonneg and v < 0.0:
                    v = 0.0
                xp[z + 1, y + 1, xx + 1] = v


@njit(parallel=True, cache=True, fastmath=True, boundscheck=False)
def _momentum_step(
    zp: NDArray[np.floating[Any]],
    gp: NDArray[np.floating[Any]],
    denom: NDArray[np.floating[Any]],
    scale: float,
    nonneg: bool,
    x_prev: NDArray[np.floating[Any]],
    gamma: float,
) -> float:
    """One OS-momentum step on padded ``zp`` (the extrapolated point): ``x = [z - scale * grad / denom]_+``,
    then ``z <- x + gamma (x - x_prev)`` and ``x_prev <- x``. Returns ``sum grad * (x - x_prev_old)`` (the
    restart test: positive when the step's gradient opposes the move)."""
    nz, ny, nx = denom.shape
    part = np.zeros(nz)
    for z in prange(nz):
        acc = 0.0
        for y in range(ny):
            for xx in range(nx):
                den = denom[z, y, xx]
                zv = zp[z + 1, y + 1, xx + 1]
                v = zv if den <= 0.0 else zv - scale * gp[z + 1, y + 1, xx + 1] / den
                if nonneg and v < 0.0:
                    v = 0.0
                old = x_prev[z, y, xx]
                acc += gp[z + 1, y + 1, xx + 1] * (v - old)
                zp[z + 1, y + 1, xx + 1] = v + gamma * (v - old)
                x_prev[z, y, xx] = v
        part[z] = acc
    return part.sum()


def statistical_weights(raw: NDArray[Any], dark: NDArray[Any], flat: NDArray[Any]) -> NDArray[np.float32]:
    """PWLS weights ~ 1/variance of the line integrals: detected counts over mean open-beam counts."""
    open_beam = float(np.mean(np.asarray(flat, dtype=np.float64) - dark))
    if not open_beam > 0:
        raise ReconError("flat field is not brighter than the dark field; cannot form statistical weights")
    return (np.maximum(np.asarray(raw, dtype=np.float32) - dark, 0.0) / open_beam).astype(np.float32)


def _zero_border(vp: NDArray[np.float32]) -> None:
    vp[[0, -1]] = 0.0
    vp[:, [0, -1]] = 0.0
    vp[:, :, [0, -1]] = 0.0


class _Pass:
    """One subset's views, walked in chunks: operator, view numbers, and chunk bounds in the operator."""

    def __init__(self, A: Projector, views: NDArray[np.intp], chunk: int) -> None:
        self.op = subset_operator(A, views)
        self.views = views
        self.chunks = [(j, min(j + chunk, views.size)) for j in range(0, views.size, chunk)]

    def read(self, stack: NDArray[np.float32] | ProjectionStack, j0: int, j1: int) -> NDArray[np.float32]:
        """Rows of ``stack`` for chunk ``j0..j1`` as float32 (a view when ``stack`` is an array and views are contiguous)."""
        return view_rows(stack, self.views[j0:j1])


class DataTerm(Protocol):
    """The data term ``0.5 sum_i w_i ([Ax]_i - y_i)^2`` of views cut into ordered subsets, as the solver needs it."""

    subsets: int

    @property
    def padded_shape(self) -> tuple[int, int, int]:
        """The padded volume's shape ``(nz + 2, ny + 2, nx + 2)``."""

    def curvature(self, out: NDArray[np.float32]) -> None:
        """Add the surrogate's data curvature ``A^T (w * A 1)`` into the padded ``out``."""

    def gradient(self, xp: NDArray[np.float32], subset: int, out: NDArray[np.float32] | None) -> float:
        """Subset ``subset``'s term at the padded ``xp``; its gradient ``A_m^T w (A_m x - y_m)`` is added into the
        padded ``out`` (skipped when None)."""


class ViewsData:
    """The data term of projections held here (arrays, or anything sliceable along views, read in chunks).

    ``subset_views``: the views of each ordered subset (default: every ``subsets``-th view, starting at each
    offset); a subset may be empty.
    """

    def __init__(
        self,
        A: Projector,
        y: NDArray[np.float32] | ProjectionStack,
        weights: NDArray[np.float32] | ProjectionStack | None,
        *,
        subsets: int = 1,
        chunk_views: int = 8,
        subset_views: list[NDArray[np.intp]] | None = None,
    ) -> None:
        subset_views = ordered_subsets(A, y, weights, subsets, subset_views)
        n_views = A.proj_shape[0]
        self.A, self.y, self.weights = A, y, weights
        self.padded_shape = A.padded_shape
        self.subsets = len(subset_views)
        self._passes = [_Pass(A, v, chunk_views) for v in subset_views]
        self._whole = _Pass(A, np.arange(n_views), chunk_views)
        self._buf = np.empty((min(chunk_views, n_views),) + A.proj_shape[1:], np.float32)
        self._no_w = np.ones((1, 1, 1), np.float32)

    def curvature(self, out: NDArray[np.float32]) -> None:
        """Add ``A^T (w * A 1)`` into the padded ``out``."""
        ones = np.zeros(self.padded_shape, np.float32)
        ones[1:-1, 1:-1, 1:-1] = 1.0
        for j0, j1 in self._whole.chunks:
            r = self.A.forward_padded(ones, self._buf[: j1 - j0], j0)
            if self.weights is not None:
                r *= self._whole.read(self.weights, j0, j1)
            self.A.back_padded(r, out, j0)

    def gradient(self, xp: NDArray[np.float32], subset: int, out: NDArray[np.float32] | None) -> float:
        """Subset ``subset``'s data term at ``xp``; its gradient added into ``out`` unless None."""
        ps = self._passes[subset]
        weighted = self.weights is not None
        value = 0.0
        if ps.op is None:  # an empty subset
            return value
        for j0, j1 in ps.chunks:
            r = ps.op.forward_padded(xp, self._buf[: j1 - j0], j0)
            w = ps.read(self.weights, j0, j1) if self.weights is not None else self._no_w
            value += _residual(r, ps.read(self.y, j0, j1), w, weighted)
            if out is not None:
                ps.op.back_padded(r, out, j0)
        return value


def pwls_sps(
    A: Projector,
    y: NDArray[np.float32] | ProjectionStack,
    weights: NDArray[np.float32] | ProjectionStack | None = None,
    *,
    beta: float = DEFAULT_BETA,
    iterations: int = 50,
    x0: NDArray[np.float32] | None = None,
    neighbourhood: int = 1,
    subsets: int = 1,
    nonneg: bool = True,
    chunk_views: int = 8,
    momentum: bool = False,
    final_cost: bool = False,
    data_curvature: NDArray[np.float32] | None = None,
    keep_data_curvature: Callable[[NDArray[np.float32]], None] | None = None,
    progress: ProgressCallback | None = None,
    callback: Callable[[int, NDArray[np.float32]], None] | None = None,
) -> PwlsResult:
    """Minimise the PWLS cost by (ordered-subset) SPS; the cost is monotone without subsets and momentum.

    With a GPU operator (:class:`recon.cuda.CudaProjector`) the data term and every volume stay on the GPU
    (:mod:`recon.cuda_pwls`). ``momentum`` adds Nesterov's momentum to the subset steps (one more volume in memory;
    see the module).
    ``final_cost`` also computes the cost at the result: one more forward projection of every view, made only when
    asked for (the costs of the earlier iterates come with their gradients). ``data_curvature`` and
    ``keep_data_curvature``: as in :func:`pwls_solve`.
    ``callback(iteration, image)`` sees the iterate after each iteration (a view: copy what you keep).
    ``y`` and ``weights`` may be arrays or anything sliceable along views (an HDF5 dataset):
    they are read ``chunk_views`` views at a time, so only the volume-sized state (iterate,
    gradient, surrogate denominators) and one chunk of projections are held in memory.
    An ``x0`` of shape ``A.padded_shape`` (the start in its interior) becomes the iterate
    itself, saving a volume: the result is then a view of its interior.
    """
    if subsets < 1 or chunk_views < 1:
        raise ReconError(f"need subsets >= 1 and chunk_views >= 1; got {subsets}, {chunk_views}")
    solve: dict[str, Any] = {
        "beta": beta,
        "iterations": iterations,
        "x0": x0,
        "neighbourhood": neighbourhood,
        "nonneg": nonneg,
        "momentum": momentum,
        "final_cost": final_cost,
        "data_curvature": data_curvature,
        "keep_data_curvature": keep_data_curvature,
        "progress": progress,
        "callback": callback,
    }
    if A.device == "cuda":  # the data term and every volume on the GPU
        from recon.cuda import CudaProjector, CudaViewsData
        from recon.cuda_pwls import pwls_solve_on_gpu

        assert isinstance(A, CudaProjector)
        return pwls_solve_on_gpu(CudaViewsData(A, y, weights, subsets=subsets), **solve)
    return pwls_solve(ViewsData(A, y, weights, subsets=subsets, chunk_views=chunk_views), **solve)


def pwls_solve(
    data: DataTerm,
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
    """:func:`pwls_sps` on any :class:`DataTerm` (projections held here, or spread over a cluster's workers).

    ``data_curvature``: ``A^T (w * A 1)`` of these views and weights, computed before (:mod:`recon.curvature`); it
    becomes the surrogate's denominator array (updated in place) and saves a forward and a back projection of every
    view. ``keep_data_curvature`` is called with it once computed, before the penalty's share is added."""
    t0 = time.perf_counter()
    padded = tuple(data.padded_shape)
    given_padded = checked_start(padded, x0, iterations, beta, data_curvature)
    in_place = given_padded is not None
    offs, omega = neighbour_offsets(neighbourhood)
    subsets = data.subsets
    # data curvature d = A^T (w * A 1), computed once into a volume of its own (or given)
    if data_curvature is not None:
        denom = data_curvature
    else:
        denom_p = np.zeros(padded, np.float32)
        data.curvature(denom_p)
        denom = denom_p[1:-1, 1:-1, 1:-1]
        del denom_p
        if keep_data_curvature is not None:
            keep_data_curvature(denom)
    beta_abs = absolute_beta(denom, beta, omega)
    _add_penalty_curvature(denom, beta_abs, offs, omega)
    gp = np.zeros(padded, np.float32)  # gradient accumulator (its border is scratch)
    if given_padded is not None:
        xp = given_padded  # the iterate, zero-bordered for the projector
        _zero_border(xp)
    else:
        xp = np.zeros(padded, np.float32)
        if x0 is not None:
            xp[1:-1, 1:-1, 1:-1] = x0
    if nonneg:
        np.maximum(xp, 0, out=xp)
    x_prev = np.array(xp[1:-1, 1:-1, 1:-1]) if momentum else None  # the last iterate; xp holds the extrapolation
    t_k, restarts = 1.0, 0
    cost: list[float] = []
    for it in range(iterations + (1 if final_cost else 0)):
        final = it == iterations
        if final and x_prev is not None:
            xp[1:-1, 1:-1, 1:-1] = x_prev  # the result is the iterate, not the extrapolated point
        data_term = 0.0
        rough = 0.0
        for m in range(subsets):
            if not final:
                gp.fill(0.0)
            data_term += data.gradient(xp, m, None if final else gp)
            if final:
                if m == 0:
                    rough = penalty_add(xp, offs, omega, 0.0, gp)
                continue  # final cost only
            # gp = A_m^T W r + beta/M grad R, so that M * gp is the full-gradient estimate
            rr = penalty_add(xp, offs, omega, beta_abs / subsets, gp)
            if m == 0:
                rough = rr
            if x_prev is None:
                _sps_step(xp, gp, denom, float(subsets), nonneg)
                continue
            t_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t_k * t_k))
            if _momentum_step(xp, gp, denom, float(subsets), nonneg, x_prev, (t_k - 1.0) / t_next) > 0.0:
                xp[1:-1, 1:-1, 1:-1] = x_prev  # overshot: restart the momentum from the iterate
                t_next, restarts = 1.0, restarts + 1
            t_k = t_next
        cost.append(float(data_term + beta_abs * rough))
        if callback is not None and not final:
            callback(it + 1, xp[1:-1, 1:-1, 1:-1] if x_prev is None else x_prev)
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
    if x_prev is not None and not final_cost:
        xp[1:-1, 1:-1, 1:-1] = x_prev  # the result is the iterate, not the extrapolated point
    del gp, denom, x_prev
    x = xp[1:-1, 1:-1, 1:-1] if in_place else np.ascontiguousarray(xp[1:-1, 1:-1, 1:-1])
    return PwlsResult(x, cost, final_cost, iterations, time.perf_counter() - t0, beta_abs, restarts)
