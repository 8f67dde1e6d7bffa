"""Joint estimation of all view corrections and all BB centres: robust sparse Levenberg-Marquardt.

Unknowns: a rigid correction per view (6 numbers, optionally intrinsics) and the BB centres (3 each).
Residuals: reprojection errors in pixels, Huber-weighted. The normal equations are solved with the Schur
complement that eliminates the (block-diagonal) view unknowns, leaving a small dense system on the BB
centres. Gauge: the BB constellation keeps the centroid, orientation and size of its first triangulation
from the nominal geometry (seven linear constraints on the centre displacements, see :func:`gauge_matrix`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from calib.model import ViewModel, ViewState, all_finite


@dataclass
class BundleResult:
    """Outcome of :func:`bundle_adjust`."""

    state: ViewState
    xyz: NDArray[np.float64]
    iterations: int
    cost_history: list[float] = field(default_factory=list)
    converged: bool = False


def gauge_matrix(xyz0: NDArray[np.float64], weights: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Seven linear constraints ``G (xyz - xyz0) = 0`` (centroid, small rotation, scale) on ``(K,3)`` -> ``(7, 3K)``;
    ``weights`` (K,) say how much each point takes part (zero: its displacement is not constrained; default all)."""
    k = xyz0.shape[0]
    w = np.ones(k) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    c = xyz0 - w @ xyz0
    scale = max(float(np.sqrt(w @ (c**2).sum(1))), 1e-9)
    c = c / scale
    G = np.zeros((7, k, 3))
    G[0:3] = np.eye(3)[:, None, :]
    # rotation: sum_k c_k x d_k = 0  ->  rows of -[c_k]_x
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        G[3 + i] = np.cross(c, e)  # e . (c x d) = (e x c) . d, sign irrelevant for a constraint
    G[6] = c
    return (G * w[None, :, None]).reshape(7, 3 * k) * np.sqrt(k)  # uniform weights: rows of norm 1/sqrt(K)


def _huber_weights(norm: NDArray[np.float64], delta: float) -> NDArray[np.float64]:
    return np.where(norm <= delta, 1.0, delta / np.maximum(norm, 1e-300))


def _huber_cost(norm: NDArray[np.float64], delta: float) -> float:
    return float(np.where(norm <= delta, 0.5 * norm**2, delta * (norm - 0.5 * delta)).sum())


def bundle_adjust(
    model: ViewModel,
    uv: NDArray[np.float64],
    xyz0: NDArray[np.float64],
    state0: ViewState | None = None,
    *,
    loss_scale_px: float = 0.5,
    max_iterations: int = 30,
    tol: float = 1e-6,
    intrinsics_prior_mm: float = 5.0,
    gauge_xyz: NDArray[np.float64] | None = None,
    gauge_weights: NDArray[np.float64] | None = None,
    pose_prior: tuple[float, float] | None = None,
    point_prior_mm: float | None = None,
    spread: NDArray[np.float64] | None = None,
    callback: Callable[[int, ViewState, NDArray[np.float64], float], None] | None = None,
) -> BundleResult:
    """Minimise the Huber reprojection cost over view corrections and BB centres (``uv`` NaN = not seen).

    The gauge is fixed by :func:`gauge_matrix` of ``gauge_xyz`` (default ``xyz0``) and ``gauge_weights``. ``spread``
    ``(N, K)`` (default 1) is each detection's expected error relative to the others: its residual is divided by it.
    ``point_prior_mm``: a weak pull of every BB centre towards ``xyz0`` (its standard deviation), so that a centre the
    views hold poorly cannot run away (rough solves of tracks that may be wrong; without it, last-bit differences of
    the linear algebra sent such centres to 1e17 mm along different paths on different CPUs)."""
    n, k = uv.shape[:2]
    seen = all_finite(uv)
    spread = np.ones((n, k)) if spread is None else np.where(seen, np.asarray(spread, dtype=float), 1.0)
    obs = np.where(seen[..., None], uv, 0.0)
    state = model.identity() if state0 is None else state0.copy()
    xyz = xyz0.copy()
    p = model.n_params
    ref = xyz0 if gauge_xyz is None else gauge_xyz
    G = gauge_matrix(ref, gauge_weights)
    prior_w = np.zeros(p)
    prior_w[6:] = 1.0 / intrinsics_prior_mm**2
    point_w = 0.0 if point_prior_mm is None else 1.0 / point_prior_mm**2
    if pose_prior is not None:  # (rad, mm): weak pull of every view towards its nominal pose
        prior_w[0:3] = 1.0 / pose_prior[0] ** 2
        prior_w[3:6] = 1.0 / pose_prior[1] ** 2

    def prior_params(st: ViewState) -> NDArray[np.float64]:
        return np.concatenate([st.rotvec, st.t, st.k], 1)

    def cost_of(st: ViewState, X: NDArray[np.float64]) -> float:
        r = model.project(st, X) - obs
        nr = np.where(seen, np.linalg.norm(r, axis=-1) / spread, 0.0)
        g = G @ (X - ref).ravel()
        return (
            _huber_cost(nr, loss_scale_px)
            + 0.5 * float((prior_w * prior_params(st) ** 2).sum())
            + 0.5 * gauge_w * float(g @ g)
            + 0.5 * point_w * float(((X - xyz0) ** 2).sum())
        )

    uv_p, Jv, Jp = model.project_jac(state, xyz)
    jpp = np.einsum("nkai,nkaj->kij", Jp * seen[..., None, None], Jp)
    gauge_w = float(np.mean(np.trace(jpp, axis1=1, axis2=2))) + 1.0
    cost = cost_of(state, xyz)
    result = BundleResult(state, xyz, 0, [cost])
    mu = 1e-3
    for it in range(1, max_iterations + 1):
        r = np.where(seen[..., None], uv_p - obs, 0.0)
        w = _huber_weights(np.linalg.norm(r, axis=-1) / spread, loss_scale_px) * seen / spread**2
        Jv_w = Jv * w[..., None, None]
        Jv_wf = Jv_w.reshape(n, 2 * k, p)
        Hvv = np.swapaxes(Jv_wf, 1, 2) @ Jv.reshape(n, 2 * k, p)
        Hvp = np.swapaxes(Jv_w, 2, 3) @ Jp  # (N,K,p,3)
        Jp_w = Jp * w[..., None, None]
        Hpp = np.swapaxes(Jp_w, 0, 1).reshape(k, 2 * n, 3).transpose(0, 2, 1) @ np.swapaxes(Jp, 0, 1).reshape(
            k, 2 * n, 3
        )
        gv = (np.swapaxes(Jv_wf, 1, 2) @ r.reshape(n, 2 * k, 1))[..., 0]
        gp = (
            np.swapaxes(Jp_w, 0, 1).reshape(k, 2 * n, 3).transpose(0, 2, 1) @ np.swapaxes(r, 0, 1).reshape(k, 2 * n, 1)
        ).ravel()
        Hvv += np.diag(prior_w)[None]
        gv += prior_w[None] * prior_params(state)
        gvec = G @ (xyz - ref).ravel()
        Hg = gauge_w * G.T @ G
        gg = gauge_w * G.T @ gvec
        accepted = False
        while not accepted:
            Hvv_d = Hvv + mu * np.einsum("nii->ni", Hvv)[..., None] * np.eye(p) + 1e-12 * np.eye(p)
            Hvv_inv = np.linalg.inv(Hvv_d)
            B = Hvp.transpose(0, 2, 1, 3).reshape(n, p, 3 * k)  # (N,p,3K)
            S = np.zeros((3 * k, 3 * k))
            for j in range(k):
                S[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] = Hpp[j] * (1.0 + mu) + point_w * np.eye(3)
            S += Hg
            HiB = Hvv_inv @ B
            S -= B.reshape(n * p, 3 * k).T @ HiB.reshape(n * p, 3 * k)
            rhs = -(gp + gg + point_w * (xyz - xyz0).ravel()) + np.einsum("npi,np->i", HiB, gv)
            try:
                dp = np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                dp = np.linalg.lstsq(S, rhs, rcond=None)[0]
            dv = -np.einsum("nij,nj->ni", Hvv_inv, gv + B @ dp)
            new_state = state.stepped(dv)
            new_xyz = xyz + dp.reshape(k, 3)
            new_cost = cost_of(new_state, new_xyz)
            if np.isfinite(new_cost) and new_cost <= cost:
                accepted = True
                mu = max(mu / 3.0, 1e-7)
            else:
                mu *= 4.0
                if mu > 1e8:
                    break
        if not accepted:
            result.converged = True
            break
        rel = (cost - new_cost) / max(cost, 1e-300)
        state, xyz, cost = new_state, new_xyz, new_cost
        result.cost_history.append(cost)
        result.iterations = it
        if callback is not None:
            callback(it, state, xyz, cost)
        uv_p, Jv, Jp = model.project_jac(state, xyz)
        step = float(np.abs(dv[:, :6]).max(initial=0.0)) + float(np.abs(dp).max(initial=0.0))
        if rel < tol or step < 1e-9:
            result.converged = True
            break
    result.state, result.xyz = state, xyz
    return result
