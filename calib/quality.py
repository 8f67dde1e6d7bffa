"""How far each view's calibrated geometry can be trusted, and views bridged from their neighbours.

A view is calibrated from its *own* BBs when they over-determine its rigid pose (at least four BBs: eight
measurements for six unknowns). A view with fewer is *bridged*: its correction is interpolated from the
nearest own views on either side and refined with its own BBs, if any, under that prior. A view too far from
any own view *fails* (NaN geometry). Every view gets a predicted error in pixels: its pose covariance (the
measured centroid noise through the bundle adjustment's Jacobian, conditional on the BB centres; for bridged
views combined with the prior) propagated to points filling the field of view.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import null_space

from calib.bundle import gauge_matrix
from calib.evaluate import fov_points
from calib.model import ViewModel, ViewState, all_finite
from orbitct.rotations import matrix_to_rotvec, rotvec_to_matrix
from orbitct.verdict import Verdict

OWN, BRIDGED, FAILED = "own", "bridged", "failed"
STATUS_CODES = {OWN: 0, BRIDGED: 1, FAILED: 2}  # /geometry/calibrated/view_status (-1: not a projection)
MIN_OWN_BBS = 4
MAX_VIEW_MISFIT = 4.0  # a view's residual RMS (dof-corrected) beyond this many centroid noises: its BBs disagree
MIN_MISFIT_PX = 0.25  # ... and beyond this: centroids of real blobs carry biases of a few tenths of a pixel


def misfit_limit_px(noise_px: float) -> float:
    """The residual RMS of a view (px, dof-corrected) beyond which its BBs disagree with its pose."""
    return max(MAX_VIEW_MISFIT * noise_px, MIN_MISFIT_PX)


@dataclass(frozen=True)
class ViewQuality:
    """Per projection view: status, BBs used, predicted error (px); and the centroid noise it assumes."""

    status: NDArray[np.str_]
    n_bbs: NDArray[np.int_]
    predicted_px: NDArray[np.float64]
    noise_px: float
    misfit_px: NDArray[np.float64]  # views with 4+ BBs: residual RMS, dof-corrected (NaN: others)

    @property
    def inconsistent(self) -> NDArray[np.bool_]:
        """Views with enough BBs whose BBs disagree with their fitted pose (failed for that reason)."""
        return np.nan_to_num(self.misfit_px) > misfit_limit_px(self.noise_px)

    def counts(self) -> dict[str, int]:
        """Views calibrated from their own BBs, bridged, failed."""
        return {s: int((self.status == s).sum()) for s in (OWN, BRIDGED, FAILED)}


def centroid_noise_px(residual_xy: NDArray[np.float64], n_params: int = 0) -> float:
    """Standard deviation of one centroid coordinate from reprojection residuals ``(..., 2)`` of a fit with
    ``n_params`` unknowns: the RMS of the residuals within five robust sigmas (gross outliers left out, heavy
    tails kept), corrected for the degrees of freedom the fit used up."""
    r = residual_xy[all_finite(residual_xy)].ravel()
    if r.size == 0:
        return float("nan")
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    kept = r[np.abs(r) <= 5.0 * mad] if mad > 0 else r
    dof = max(kept.size - n_params * kept.size / r.size, 1.0)
    return float(np.sqrt((kept**2).sum() / dof))


def rigid_pose_normal(
    model: ViewModel, state: ViewState, xyz: NDArray[np.float64], uv: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Gauss-Newton normal matrix ``J^T J`` ``(N,6,6)`` and gradient ``J^T r`` ``(N,6)`` of the rigid pose."""
    pred, Jv, _ = model.project_jac(state, xyz)
    seen = all_finite(uv)
    r = np.where(seen[..., None], pred - np.nan_to_num(uv), 0.0)
    J = (Jv[..., :6] * seen[..., None, None]).reshape(len(pred), -1, 6)
    return np.swapaxes(J, 1, 2) @ J, (np.swapaxes(J, 1, 2) @ r.reshape(len(pred), -1, 1))[..., 0]


def fit_rigid_poses(
    model: ViewModel, state: ViewState, xyz: NDArray[np.float64], uv: NDArray[np.float64], iterations: int = 5
) -> ViewState:
    """Each view's rigid pose refitted to its detections ``uv`` (NaN = not used) of the BBs ``xyz``, all views at
    once (Gauss-Newton from ``state``; the BB centres and intrinsics stay)."""
    st = state
    for _ in range(iterations):
        H, g = rigid_pose_normal(model, st, xyz, uv)
        step = -np.linalg.solve(H + 1e-9 * np.eye(6), g[..., None])[..., 0]
        st = st.stepped(np.concatenate([step, np.zeros((len(step), model.n_intrinsics))], 1))
    return st


def _marginal_pose_covariance(
    model: ViewModel,
    state: ViewState,
    xyz: NDArray[np.float64],
    uv: NDArray[np.float64],
    variance: NDArray[np.float64] | None = None,
    slope: NDArray[np.float64] | None = None,
    bias: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Per view, the rigid pose's covariance ``(N,6,6)`` for unit centroid noise, the BB centres' own
    uncertainty included: ``H_vv^-1 + H_vv^-1 H_vp C_p H_pv H_vv^-1``, where ``C_p`` inverts the Schur complement
    on the centres in the gauge that holds the constellation's centroid, orientation and size (a similarity of
    the whole solution changes no pixel error measured after similarity alignment).

    ``variance`` ``(N,K,2,2)``: each detection's noise covariance relative to the unit one (the identity
    everywhere: the formula above). The bundle adjustment weights every detection alike, so unequal noise enters
    as the sandwich ``H^-1 M H^-1`` (``M`` the normal matrix with the noise covariances inside), pose blocks only.
    ``slope`` ``(N,K,2,2)``: each detection's weight in ``H`` (a robust loss's expected derivative, see
    :func:`huber_moments`; the identity by default), applied as its square root to the Jacobians. ``bias``
    ``(N,K,2)``: a known offset of each detection (in the units of the noise): the pose error it causes, solved
    through the same normal equations (BB centres free, gauge held), enters as its outer product."""
    _, Jv, Jp = model.project_jac(state, xyz)
    seen = all_finite(uv)
    n, k = seen.shape
    Jv = Jv[..., :6] * seen[..., None, None]
    Jp = Jp * seen[..., None, None]
    if (
        slope is not None
        and not slope[..., 0, 1].any()
        and not slope[..., 1, 0].any()
        and np.array_equal(slope[..., 0, 0], slope[..., 1, 1])
    ):  # A = a I (weighted least squares): scale
        root = np.sqrt(np.maximum(slope[..., 0, 0], 1e-9))
        Jv, Jp = Jv * root[..., None, None], Jp * root[..., None, None]
        base = np.broadcast_to(np.eye(2), slope.shape) if variance is None else variance
        variance = base / (root**2)[..., None, None]
        if bias is not None:
            bias = bias * root[..., None]
    elif slope is not None:  # H = sum J^T A J: Jacobians times A^1/2, noise covariance V -> A^-1/2 V A^-1/2
        lam, vec = np.linalg.eigh(slope)
        lam = np.maximum(lam, 1e-9)
        half = np.einsum("...ab,...b,...cb->...ac", vec, np.sqrt(lam), vec)
        inv_half = np.einsum("...ab,...b,...cb->...ac", vec, 1.0 / np.sqrt(lam), vec)
        Jv, Jp = np.matmul(half, Jv), np.matmul(half, Jp)
        base = np.broadcast_to(np.eye(2), slope.shape) if variance is None else variance
        variance = inv_half @ base @ inv_half
        if bias is not None:
            bias = np.einsum("...ab,...b->...a", half, bias)
    Hvv = np.einsum("nkai,nkaj->nij", Jv, Jv) + 1e-9 * np.eye(6)
    Hvp = np.einsum("nkai,nkaj->nikj", Jv, Jp).reshape(n, 6, 3 * k)
    Hpp = np.einsum("nkai,nkaj->kij", Jp, Jp)
    Hvv_inv = np.linalg.inv(Hvv)
    A = Hvv_inv @ Hvp  # (N, 6, 3K)
    S = -(np.swapaxes(Hvp, 1, 2) @ A).sum(0)
    for j in range(k):
        S[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] += Hpp[j]
    Nb = null_space(gauge_matrix(xyz))  # (3K, 3K-7): displacements that keep the gauge
    Cp = Nb @ np.linalg.pinv(Nb.T @ S @ Nb, hermitian=True) @ Nb.T
    shifted = 0.0
    if bias is not None:  # H delta = J^T b: Schur on the centres, then each view's pose
        b = np.where(seen[..., None], np.nan_to_num(bias), 0.0)
        g_v = np.einsum("nkai,nka->ni", Jv, b)
        g_p = np.einsum("nkai,nka->ki", Jp, b).reshape(3 * k)
        d_p = Cp @ (g_p - np.einsum("nix,ni->x", A, g_v))
        d_v = np.einsum("nij,nj->ni", Hvv_inv, g_v) - A @ d_p
        shifted = np.einsum("ni,nj->nij", d_v, d_v)
    if variance is None:
        return Hvv_inv + A @ Cp @ np.swapaxes(A, 1, 2) + shifted
    # the inverse normal matrix, rows of view n: G_n = [Hvv_n^-1 at n] + A_n Cp R with R = [A_1^T ... A_N^T, -I]
    VJv = np.matmul(variance, Jv)  # unseen detections are zero in Jv and Jp already
    Mvv = np.matmul(np.swapaxes(Jv.reshape(n, 2 * k, 6), 1, 2), VJv.reshape(n, 2 * k, 6))
    Mvp = np.einsum("nkai,nkaj->nikj", VJv, Jp).reshape(n, 6, 3 * k)
    Mpp = np.zeros((3 * k, 3 * k))
    for j, block in enumerate(np.einsum("nkai,nkaj->kij", Jp, np.matmul(variance, Jp))):
        Mpp[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] = block
    At = np.swapaxes(A, 1, 2)
    RMD = (At @ Mvv - np.swapaxes(Mvp, 1, 2)) @ Hvv_inv  # R M D_n^T, (N, 3K, 6)
    AtMvp = (At @ Mvp).sum(0)
    RMR = (At @ Mvv @ A).sum(0) - AtMvp - AtMvp.T + Mpp
    cross = A @ Cp @ RMD
    return Hvv_inv @ Mvv @ Hvv_inv + cross + np.swapaxes(cross, 1, 2) + A @ (Cp @ RMR @ Cp) @ At + shifted


#: the bundle's Huber threshold before the centroid noise is measured (px), and the most it ever is
FIRST_LOSS_SCALE_PX = 0.5


def huber_threshold_px(noise_px: float) -> float:
    """The bundle's Huber threshold for a scan whose centroid noise measured ``noise_px``: 1.5 times it, within
    0.02 px and :data:`FIRST_LOSS_SCALE_PX` (the first solve's, also the threshold where the noise is unknown)."""
    return float(np.clip(1.5 * noise_px, 0.02, FIRST_LOSS_SCALE_PX)) if np.isfinite(noise_px) else FIRST_LOSS_SCALE_PX


def huber_moments(
    covariance: NDArray[np.float64], loss_scale_px: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """For detections with Gaussian noise ``covariance`` ``(..., 2, 2)`` (px^2) fitted with the bundle's Huber loss on
    the residual's length (threshold ``loss_scale_px``): the expected derivative of the influence ``psi(r)``, which
    takes the place of the identity in the normal matrix, and ``E[psi psi^T]``, which takes the place of the noise
    covariance (``psi(r) = r min(1, delta / |r|)``; 6 x 6 Gauss-Hermite nodes). A detection far noisier than the
    threshold counts about ``delta / |r|`` as much: the fit never lets it pull with its full error."""
    t, w = np.polynomial.hermite_e.hermegauss(6)
    z0, z1 = (v.ravel() for v in np.meshgrid(t, t, indexing="ij"))  # standard normal nodes
    wz = np.outer(w, w).ravel() / (2 * np.pi)
    half = z0 > 0  # every moment below is even in the residual: the nodes at -z count as those at z
    z0, z1, wz = z0[half], z1[half], 2.0 * wz[half]
    c = np.asarray(covariance, float)
    l00 = np.sqrt(np.maximum(c[..., 0, 0], 1e-24))
    l10 = c[..., 1, 0] / l00
    l11 = np.sqrt(np.maximum(c[..., 1, 1] - l10**2, 1e-24))
    r0 = l00[..., None] * z0  # (..., Q): the residual at each node
    r1 = l10[..., None] * z0 + l11[..., None] * z1
    n = np.maximum(np.hypot(r0, r1), 1e-12)
    scale = np.minimum(1.0, loss_scale_px / n)
    out = n > loss_scale_px
    u0, u1 = r0 / n, r1 / n
    s2 = scale**2
    spread = np.stack(
        [
            np.stack([(r0 * r0 * s2) @ wz, (r0 * r1 * s2) @ wz], -1),
            np.stack([(r0 * r1 * s2) @ wz, (r1 * r1 * s2) @ wz], -1),
        ],
        -2,
    )
    d00 = np.where(out, scale * (1.0 - u0 * u0), 1.0) @ wz
    d01 = np.where(out, -scale * u0 * u1, 0.0) @ wz
    d11 = np.where(out, scale * (1.0 - u1 * u1), 1.0) @ wz
    slope = np.stack([np.stack([d00, d01], -1), np.stack([d01, d11], -1)], -2)
    return slope, spread


def _predicted_px(model: ViewModel, state: ViewState, cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """RMS over field-of-view points of the 2-D projection error implied by pose covariances ``(N,6,6)``."""
    pts = fov_points(model.nominal, 4)
    _, Jv, _ = model.project_jac(state, pts)
    J = Jv[..., :6]  # (N, M, 2, 6)
    var = np.einsum("nmai,nij,nmaj->n", J, cov, J) / pts.shape[0]
    return np.sqrt(np.maximum(var, 0.0))


def placement_predicted_px(
    model: ViewModel,
    xyz: NDArray[np.float64],
    uv: NDArray[np.float64],
    noise_px: float,
    variance: NDArray[np.float64] | None = None,
    loss_scale_px: float | None = None,
    bias_px: NDArray[np.float64] | None = None,
    spread: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Per view, the predicted error (px, RMS over field-of-view points) of a calibration of BBs ``xyz`` seen at
    ``uv`` (NaN = not seen) with centroid noise ``noise_px`` (each detection's covariance ``noise_px**2`` times
    ``variance`` ``(N,K,2,2)``, when given) and known offsets ``bias_px`` ``(N,K,2)``, at the nominal views
    (planning: nothing measured); with ``loss_scale_px``, fitted with the bundle's Huber loss of that threshold
    (:func:`huber_moments`; the offsets count in the loss's weights as a spread); with ``spread`` ``(N,K)``, each
    residual divided by it first, as the bundle does with :func:`calib.detect.detection_spread`."""
    state = model.identity()
    rel = np.broadcast_to(np.eye(2), uv.shape[:2] + (2, 2)) if variance is None else np.nan_to_num(variance)
    s2 = np.ones(uv.shape[:2] + (1, 1)) if spread is None else (np.nan_to_num(spread, nan=1.0) ** 2)[..., None, None]
    if loss_scale_px is None:  # weighted least squares: H = J^T J / s^2, M = J^T V J / s^4
        rel_bias = None if bias_px is None else bias_px / noise_px
        slope = None if spread is None else np.broadcast_to(np.eye(2), rel.shape) / s2
        base = variance if spread is None else rel / s2**2
        return _predicted_px(
            model, state, noise_px**2 * _marginal_pose_covariance(model, state, xyz, uv, base, slope, rel_bias)
        )
    total = noise_px**2 * rel
    if bias_px is not None:
        total = total + np.einsum("...a,...b->...ab", np.nan_to_num(bias_px), np.nan_to_num(bias_px))
    # the Huber loss acts on the residual over its spread: its moments there, the weights 1 / s^2 on the Jacobians
    slope, _ = huber_moments(total / s2, loss_scale_px)
    _, moment = huber_moments(noise_px**2 * rel / s2, loss_scale_px)
    return _predicted_px(
        model, state, _marginal_pose_covariance(model, state, xyz, uv, moment / s2, slope / s2, bias_px)
    )


def pose_predicted_px(
    model: ViewModel, state: ViewState, xyz: NDArray[np.float64], uv: NDArray[np.float64], noise_px: float
) -> NDArray[np.float64]:
    """Per view, the predicted error (px, RMS over field-of-view points) of a rigid pose fitted to ``uv`` with the
    BB centres ``xyz`` taken as known and centroid noise ``noise_px`` (while a scan runs: the centres come from many
    views, the pose from one)."""
    H, _ = rigid_pose_normal(model, state, xyz, uv)
    cov = noise_px**2 * np.linalg.inv(H + 1e-9 * np.eye(6)).astype(np.float64)
    return _predicted_px(model, state, cov)


def view_misfit_px(
    model: ViewModel, state: ViewState, xyz: NDArray[np.float64], uv: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Per view, the residual RMS corrected for the six pose parameters, ``sqrt(sum r^2 / (2n - 6))``: about the
    centroid noise when its detections fit its pose; large when one belongs to another BB or the object
    moved (NaN without redundancy)."""
    r = model.project(state, xyz) - uv
    seen = all_finite(r)
    dof = 2 * seen.sum(1) - 6
    ss = np.where(seen[..., None], r, 0.0) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(dof > 0, np.sqrt(ss.sum((1, 2)) / np.maximum(dof, 1)), np.nan)


def _interpolated(
    state: ViewState, own: NDArray[np.bool_], max_gap: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Correction ``(N,6)`` (rotation vector, shift) interpolated from own views, and each view's distance in
    views to the nearest own view (``inf`` where a gap is wider than ``max_gap``, or an end is farther)."""
    n = len(own)
    idx = np.flatnonzero(own)
    c = np.concatenate([matrix_to_rotvec(state.R), state.t], 1)
    out = np.full((n, 6), np.nan)
    dist = np.full(n, np.inf)
    if idx.size == 0:
        return out, dist, c
    i = np.arange(n)
    right = np.clip(np.searchsorted(idx, i), 0, idx.size - 1)
    left = np.clip(right - 1, 0, idx.size - 1)
    a, b = idx[left], idx[right]
    inside = (a < i) & (i < b)
    w = np.where(inside, (i - a) / np.maximum(b - a, 1), 0.0)[:, None]
    out[inside] = ((1 - w) * c[a] + w * c[b])[inside]
    gap_ok = inside & (b - a - 1 <= max_gap)
    dist[gap_ok] = np.minimum(i - a, b - i)[gap_ok]
    ends = ~inside  # before the first or after the last own view: hold the nearest one
    near = np.where(np.abs(a - i) <= np.abs(b - i), a, b)
    out[ends] = c[near[ends]]
    end_ok = ends & (np.abs(near - i) <= max_gap // 2)
    dist[end_ok] = np.abs(near - i)[end_ok]
    dist[own] = 0.0
    return out, dist, c


def assess_views(
    model: ViewModel,
    state: ViewState,
    xyz: NDArray[np.float64],
    uv: NDArray[np.float64],
    *,
    noise_px: float,
    max_gap: int = 10,
    min_own_bbs: int = MIN_OWN_BBS,
) -> tuple[ViewState, ViewQuality]:
    """Bridge the views without enough BBs of their own and predict every view's error.

    ``state`` holds the bundle's corrections for the own views (others are ignored); returns the states of
    all views (NaN for failed ones) and their quality."""
    n = model.nominal.n_views
    n_bbs = all_finite(uv).sum(1)
    own = n_bbs >= min_own_bbs
    misfit = np.full(n, np.nan)
    if own.any():
        o = np.flatnonzero(own)
        misfit[o] = view_misfit_px(
            ViewModel(model.nominal[o], model.intrinsics), ViewState(state.R[o], state.t[o], state.k[o]), xyz, uv[o]
        )
    inconsistent = np.nan_to_num(misfit) > misfit_limit_px(noise_px)
    own &= ~inconsistent  # neither its own pose nor an anchor for its neighbours
    sigma2 = max(noise_px, 1e-3) ** 2
    prior_c, dist, c = _interpolated(state, own, max_gap)
    status = np.where(own, OWN, np.where(np.isfinite(dist) & ~inconsistent, BRIDGED, FAILED)).astype("<U7")
    # random-walk prior: the variance of a step between neighbouring own views, times the distance in views
    idx = np.flatnonzero(own)
    if idx.size >= 3:
        steps = np.diff(c[idx], axis=0) ** 2 / np.diff(idx)[:, None]
        q = np.median(steps, axis=0) + 1e-12
    else:
        q = np.array([1e-4] * 3 + [1.0] * 3)
    R = state.R.copy()
    t = state.t.copy()
    k = state.k.copy()
    cov = np.full((n, 6, 6), np.nan)
    if idx.size:
        cov[idx] = sigma2 * _marginal_pose_covariance(
            ViewModel(model.nominal[idx], model.intrinsics), ViewState(R[idx], t[idx], k[idx]), xyz, uv[idx]
        )
    br = np.flatnonzero(status == BRIDGED)
    if br.size:
        R[br] = rotvec_to_matrix(prior_c[br, :3])
        t[br] = prior_c[br, 3:]
        k[br] = 0.0 if k.shape[1] == 0 else np.nanmedian(k[idx], axis=0) if idx.size else 0.0
        P_inv = 1.0 / (q[None] * np.maximum(dist[br], 1.0)[:, None])  # (B, 6) diagonal prior precision
        sub = ViewModel(model.nominal[br], model.intrinsics)
        st = ViewState(R[br], t[br], k[br])
        delta = np.zeros((br.size, 6))
        for _ in range(5):  # MAP Gauss-Newton of each bridged view under its prior, with its own BBs if any
            H, g = rigid_pose_normal(sub, st, xyz, uv[br])
            A = H / sigma2 + P_inv[:, :, None] * np.eye(6)
            rhs = g / sigma2 + P_inv * delta
            step = -np.linalg.solve(A, rhs[..., None])[..., 0]
            delta = delta + step
            st = st.stepped(np.concatenate([step, np.zeros((br.size, st.k.shape[1]))], 1))
        H, _ = rigid_pose_normal(sub, st, xyz, uv[br])
        cov[br] = np.linalg.inv(H / sigma2 + P_inv[:, :, None] * np.eye(6))
        R[br], t[br], k[br] = st.R, st.t, st.k
    bad = status == FAILED
    R[bad] = np.nan
    t[bad] = np.nan
    full = ViewState(R, t, k)
    predicted = np.full(n, np.nan)
    good = ~bad
    if good.any():
        g_idx = np.flatnonzero(good)
        predicted[g_idx] = _predicted_px(
            ViewModel(model.nominal[g_idx], model.intrinsics), ViewState(R[g_idx], t[g_idx], k[g_idx]), cov[g_idx]
        )
    return full, ViewQuality(status, n_bbs, predicted, float(noise_px), misfit)


def _frames(frames: NDArray[np.intp]) -> str:
    return f"frames {frames[:10].tolist()}{' ...' if frames.size > 10 else ''}"


@dataclass(frozen=True)
class CalibrationVerdict(Verdict):
    """The quality check of a calibration: its :class:`~orbitct.verdict.Verdict` and the figures behind it."""

    counts: dict[str, int] = field(default_factory=dict)
    predicted_px_median: float = float("nan")
    predicted_px_max: float = float("nan")
    worst_frame: int | None = None
    noise_px: float = float("nan")
    threshold_px: float = float("nan")

    def line(self) -> str:
        """One line for people: the views by kind, the predicted error, the noise it assumes."""
        v = self.counts
        worst = f" (frame {self.worst_frame})" if self.worst_frame is not None else ""
        return (
            f"views: {v[OWN]} from their own BBs, {v[BRIDGED]} bridged, {v[FAILED]} failed; predicted error "
            f"median {self.predicted_px_median:.3f} px, max {self.predicted_px_max:.3f} px{worst}; centroid "
            f"noise {self.noise_px:.3f} px"
        )

    def summary(self) -> dict[str, object]:
        """JSON-ready."""
        return {
            **super().summary(),
            "passed": self.passed,
            "views": dict(self.counts),
            "predicted_px_median": self.predicted_px_median,
            "predicted_px_max": self.predicted_px_max,
            "worst_frame": self.worst_frame,
            "centroid_noise_px": self.noise_px,
            "max_predicted_px": self.threshold_px,
        }

    def attrs(self) -> dict[str, object]:
        """Attributes of ``/geometry/calibrated``."""
        return {
            **super().attrs(),
            "quality": "passed" if self.passed else "failed",
            "quality_reasons_json": list(self.reasons),
            "n_views_own": self.counts[OWN],
            "n_views_bridged": self.counts[BRIDGED],
            "n_views_failed": self.counts[FAILED],
            "predicted_px_median": self.predicted_px_median,
            "predicted_px_max": self.predicted_px_max,
            "centroid_noise_px": self.noise_px,
            "max_predicted_px": self.threshold_px,
        }


def judge(
    quality: ViewQuality, frames: NDArray[np.intp], threshold_px: float, max_gap: int, method: str
) -> CalibrationVerdict:
    """The verdict on a calibration's views: failed views, or a predicted error above ``threshold_px``, fail it."""
    counts = quality.counts()
    reasons: list[str] = []
    warnings: list[str] = []
    odd = quality.inconsistent
    failed = frames[(quality.status == FAILED) & ~odd]
    need = (
        "BBs than its pose needs"
        if method == "paper"
        else f"than {MIN_OWN_BBS} BBs and lie more than {max_gap} views from a view that has them"
    )
    if failed.size:
        reasons.append(f"{failed.size} of {frames.size} view(s) failed (fewer {need}; NaN geometry): {_frames(failed)}")
    if odd.any():
        reasons.append(
            f"{int(odd.sum())} view(s) failed because their BBs disagree with their own pose (residual RMS up "
            f"to {float(np.nanmax(quality.misfit_px)):.2f} px, allowed {misfit_limit_px(quality.noise_px):.2f} px: "
            f"a BB taken for another, or the object moved): {_frames(frames[odd])}"
        )
    bridged = frames[quality.status == BRIDGED]
    if bridged.size:
        warnings.append(
            f"{bridged.size} view(s) bridged from their neighbours (fewer than {MIN_OWN_BBS} BBs of their "
            f"own): {_frames(bridged)}"
        )
    pred = quality.predicted_px
    fin = np.isfinite(pred)
    med = float(np.median(pred[fin])) if fin.any() else float("nan")
    worst = int(np.nanargmax(pred)) if fin.any() else None
    top = float(pred[worst]) if worst is not None else float("nan")
    if worst is not None and top > threshold_px:
        over = frames[fin & (pred > threshold_px)]
        reasons.append(
            f"{over.size} view(s) have a predicted error above {threshold_px:g} px (max_predicted_px), "
            f"up to {top:.2f} px at frame {int(frames[worst])}: {_frames(over)}"
        )
    if not np.isfinite(quality.noise_px):
        reasons.append("the centroid noise could not be measured (no residuals)")
    return CalibrationVerdict(
        reasons=tuple(reasons),
        warnings=tuple(warnings),
        counts=counts,
        predicted_px_median=med,
        predicted_px_max=top,
        worst_frame=None if worst is None else int(frames[worst]),
        noise_px=float(quality.noise_px),
        threshold_px=float(threshold_px),
    )


__all__ = [
    "BRIDGED",
    "FAILED",
    "FIRST_LOSS_SCALE_PX",
    "MAX_VIEW_MISFIT",
    "MIN_OWN_BBS",
    "OWN",
    "STATUS_CODES",
    "CalibrationVerdict",
    "ViewQuality",
    "assess_views",
    "centroid_noise_px",
    "fit_rigid_poses",
    "huber_moments",
    "huber_threshold_px",
    "judge",
]
