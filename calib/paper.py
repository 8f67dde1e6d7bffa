"""The published method (Ma et al., SPIE 2022), faithfully: alternate BB centres and per-view geometry.

Each iteration: (1) every BB centre is the mean of the midpoints of the common perpendiculars of all
pairs of its back-projected rays; (2) every view's rigid correction minimises the mean distance from the
BB centres to the view's back-projected rays (Eq. 2; solved per view by iteratively reweighted
Gauss-Newton, all views at once, in place of MATLAB's fmincon).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from calib.model import ViewModel, ViewState, all_finite, skew
from calib.rays import marker_rays, pairwise_midpoint_mean


def _ray_frame(
    model: ViewModel, state: ViewState, uv: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Source and unit ray directions in the (intrinsics-changed) nominal view frame, which moves rigidly."""
    return marker_rays(model.base(state.k), uv)


def fit_views_to_points(
    model: ViewModel,
    uv: NDArray[np.float64],
    xyz: NDArray[np.float64],
    state: ViewState,
    *,
    iterations: int = 30,
    eps_mm: float = 1e-6,
) -> ViewState:
    """Per view, the rigid correction minimising the mean BB-centre-to-ray distance (views independent)."""
    seen = all_finite(uv)
    origin, direction = _ray_frame(model, state, np.where(seen[..., None], uv, 0.0))
    proj = np.eye(3) - direction[..., :, None] * direction[..., None, :]  # (N,K,3,3)
    st = state.copy()
    n = uv.shape[0]

    def distances(s: ViewState) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        Y = np.einsum("nji,nkj->nki", s.R, xyz[None] - s.t[:, None])
        r = np.einsum("nkij,nkj->nki", proj, Y - origin)
        return Y, r

    Y, r = distances(st)
    cost = np.where(seen, np.linalg.norm(r, axis=-1), 0.0).sum(1)
    mu = np.full(n, 1e-3)
    for _ in range(iterations):
        d = np.linalg.norm(r, axis=-1)
        w = seen / np.maximum(d, eps_mm)  # IRLS weights for the sum of distances
        J = np.empty(r.shape + (6,))
        J[..., 0:3] = proj @ skew(Y)
        J[..., 3:6] = -proj @ np.swapaxes(st.R, 1, 2)[:, None]
        Jw = J * w[..., None, None]
        H = np.einsum("nkai,nkaj->nij", Jw, J)
        g = np.einsum("nkai,nka->ni", Jw, r)
        H += (mu[:, None] * np.einsum("nii->ni", H))[..., None] * np.eye(6) + 1e-12 * np.eye(6)
        step = -np.linalg.solve(H, g[..., None])[..., 0]
        trial = st.stepped(np.concatenate([step, np.zeros((n, model.n_intrinsics))], 1))
        Yt, rt = distances(trial)
        new_cost = np.where(seen, np.linalg.norm(rt, axis=-1), 0.0).sum(1)
        better = new_cost <= cost
        st.R[better], st.t[better] = trial.R[better], trial.t[better]
        Y[better], r[better], cost[better] = Yt[better], rt[better], new_cost[better]
        mu = np.where(better, np.maximum(mu / 3, 1e-9), mu * 4)
        if np.abs(step[better]).max(initial=0.0) < 1e-10 and better.all():
            break
    return st


def paper_calibrate(
    model: ViewModel,
    uv: NDArray[np.float64],
    *,
    iterations: int = 3,
    callback: Callable[[int, ViewState, NDArray[np.float64]], None] | None = None,
) -> tuple[ViewState, NDArray[np.float64]]:
    """Alternate BB centres (pairwise ray midpoints) and per-view corrections; ``callback(i, state, xyz)``
    is called with the initial estimate (i = 0) and after each iteration, xyz re-estimated from that state."""
    state = model.identity()
    xyz = pairwise_midpoint_mean(*marker_rays(model.geometry(state), uv))
    if callback is not None:
        callback(0, state, xyz)
    for i in range(1, iterations + 1):
        state = fit_views_to_points(model, uv, xyz, state)
        xyz = pairwise_midpoint_mean(*marker_rays(model.geometry(state), uv))
        if callback is not None:
            callback(i, state, xyz)
    return state, xyz
