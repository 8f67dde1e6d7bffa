"""The second looks of a calibration: reassign, track again, split merged blobs, drop misfits, polish.

Each step solves again from the first solution and is kept only where its verdict is better."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from calib.bundle import bundle_adjust
from calib.errors import NoMarkersError
from calib.identify import (
    assign_by_pose,
    fill_states,
    neighbour_states,
    placed_by_similarity,
    recover_missed,
    twin_constellation,
    usable_views,
)
from calib.model import ViewModel, ViewState, all_finite
from calib.options import CalibrationOptions
from calib.paper import paper_calibrate
from calib.quality import (
    FAILED,
    FIRST_LOSS_SCALE_PX,
    MIN_OWN_BBS,
    OWN,
    CalibrationVerdict,
    ViewQuality,
    assess_views,
    centroid_noise_px,
    fit_rigid_poses,
    huber_threshold_px,
    judge,
    misfit_limit_px,
    view_misfit_px,
)
from calib.rays import marker_rays, rpe_per_frame, triangulate_least_squares
from calib.split import FrameWindows, SplitSettings, fit_pair, isolated, merged_pairs, radial_profile
from calib.track import TrackingSettings
from orbitct.geometry import ViewGeometry
from orbitct.progress import ProgressCallback, report
from orbitct.scanfile import ScanFile

SPLIT_MIN_SHARE = 0.01  # blobs of two BBs are split when there are at least this share of the detections


def residual_px(geometry: ViewGeometry, uv: NDArray[np.float64], xyz: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.linalg.norm(geometry.project(xyz) - uv, axis=-1)


def reassign(
    cands: list[NDArray[np.float64]],
    model: ViewModel,
    tset: TrackingSettings,
    outcome: tuple[Any, ...],
    verdict: CalibrationVerdict,
    proj: NDArray[np.intp],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    *,
    must_improve: bool = True,
) -> tuple[tuple[Any, ...], CalibrationVerdict]:
    """Assign the detections again, to every BB predicted through the calibrated geometry (views not calibrated
    from their own BBs: through their nearest view that is), and estimate again; kept when it passes where the
    first did not, or calibrates more views from their own BBs (not ``must_improve``: unless it fails where the
    first passed or calibrates fewer views from their own BBs). Tracking predicts through rough poses, which
    miss BBs in views that see few of them (a truncating panel) or jump far (a robotic arm)."""
    xyz, state, uv = outcome[1], outcome[2], outcome[3]
    solved = outcome[7].status == OWN
    if not solved.any():
        return outcome, verdict
    filled = fill_states(ViewState(np.nan_to_num(state.R), np.nan_to_num(state.t), state.k), solved, len(solved))
    again = assign_by_pose(cands, model, filled, xyz, tset)
    if np.array_equal(again, uv, equal_nan=True):
        return outcome, verdict
    outcome, verdict, _ = estimate_again(model, again, proj, opt, progress, outcome, verdict, must_improve=must_improve)
    return outcome, verdict


def estimate_again(
    model: ViewModel,
    uv: NDArray[np.float64],
    proj: NDArray[np.intp],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    outcome: tuple[Any, ...],
    verdict: CalibrationVerdict,
    *,
    must_improve: bool = False,
    polish: Polish | None = None,
) -> tuple[tuple[Any, ...], CalibrationVerdict, bool]:
    """Estimate again from detections ``uv`` (or, with ``polish``, solve once more from a previous outcome):
    that outcome and verdict (and True) unless it fails where the first passed or calibrates fewer views from their
    own BBs (or, ``must_improve``, does no better on both)."""
    try:
        second = estimate("bundle", model, uv, opt, progress, polish)
    except NoMarkersError:
        return outcome, verdict, False
    second_verdict = judge(second[7], proj, opt.max_predicted_px, opt.bridge_max_views, "bundle")
    new, old = (second_verdict.passed, second_verdict.counts["own"]), (verdict.passed, verdict.counts["own"])
    if new > old or (new == old and not must_improve):
        return second, second_verdict, True
    return outcome, verdict, False


def recover_missed_bbs(
    cands: list[NDArray[np.float64]],
    model: ViewModel,
    tset: TrackingSettings,
    outcome: tuple[Any, ...],
    verdict: CalibrationVerdict,
    proj: NDArray[np.intp],
    diameter_mm: float,
    min_obs: int,
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    frags: NDArray[np.float64],
) -> tuple[tuple[Any, ...], CalibrationVerdict, int]:
    """Look for BBs that identification lost (:func:`calib.identify.recover_missed`) among the 2-D tracks ``frags``
    it was given, through the calibrated views; with any found, assign and estimate again with them; kept unless it
    fails where the first passed or calibrates fewer views from their own BBs. Also the number found."""
    geometry, xyz, state = outcome[0], outcome[1], outcome[2]
    solved = outcome[7].status == OWN
    if not solved.any():
        return outcome, verdict, 0
    missed = recover_missed(cands, geometry, xyz, frags, tset, min_obs, diameter_mm)
    if not len(missed):
        return outcome, verdict, 0
    filled = fill_states(ViewState(np.nan_to_num(state.R), np.nan_to_num(state.t), state.k), solved, len(solved))
    again = assign_by_pose(cands, model, filled, np.concatenate([xyz, missed]), tset)
    outcome, verdict, kept = estimate_again(model, again, proj, opt, progress, outcome, verdict)
    return outcome, verdict, len(missed) if kept else 0


def merge_twins(
    model: ViewModel,
    outcome: tuple[Any, ...],
    verdict: CalibrationVerdict,
    proj: NDArray[np.intp],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
) -> tuple[tuple[Any, ...], CalibrationVerdict, int]:
    """BBs identified twice, once in each of two parts of the orbit that nothing else ties together
    (:func:`calib.identify.twin_constellation`; experiment C at 512 px: every track broke at one frame, and the
    second half calibrated as a constellation of its own, 8-22 px off, and passed). Each pair is made one BB (the
    detections of both; in a frame that saw both, neither) and the geometry estimated again. That result replaces
    the split one whatever its verdict; where it cannot be estimated, the split one stands, failed. Also how many
    pairs were merged."""
    xyz, uv = outcome[1], outcome[3]
    pairs = twin_constellation(xyz, uv)
    if not pairs:
        return outcome, verdict, 0
    merged = uv.copy()
    for a, b in pairs:
        has_a, has_b = all_finite(merged[:, a]), all_finite(merged[:, b])
        merged[~has_a & has_b, a] = merged[~has_a & has_b, b]
        merged[has_a & has_b, a] = np.nan
    merged = np.delete(merged, [b for _, b in pairs], axis=1)
    try:
        again = estimate("bundle", model, merged, opt, progress)
    except NoMarkersError:
        reason = (
            f"{len(pairs)} BBs were identified twice, in two parts of the orbit that nothing ties together "
            "(tracking broke for every BB at once): those parts' geometries can be far apart"
        )
        return outcome, replace(verdict, reasons=(*verdict.reasons, reason)), 0
    return again, judge(again[7], proj, opt.max_predicted_px, opt.bridge_max_views, "bundle"), len(pairs)


#: views either side that :func:`sparse_views_again` compares a view's BB count with
_AROUND = 3


def sparse_views_again(
    cands: list[NDArray[np.float64]],
    model: ViewModel,
    tset: TrackingSettings,
    outcome: tuple[Any, ...],
    verdict: CalibrationVerdict,
    proj: NDArray[np.intp],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
) -> tuple[tuple[Any, ...], CalibrationVerdict, int]:
    """Views left with :data:`MIN_OWN_BBS` BBs or fewer where the views around them (three either side) see at
    least two more: frames that jumped, where tracking kept few blobs, perhaps wrong ones that a pose with two
    measurements to spare absorbs (experiment C at 512 px: two of four blobs wrong, views 5.8 and 7 px off and
    passing, a bridged neighbour with them). Their BBs are assigned again through the poses of the views around
    them (``tset``: the orbit's own jitter), or through the view's pose fitted to its own BBs where that finds
    more (frames that jump farther than the BBs lie apart), and the geometry estimated again with the views that
    gain BBs; kept unless worse. Also how many views gained."""
    state, uv, quality = outcome[2], outcome[3], outcome[7]
    count = all_finite(uv).sum(1)
    if count.size < 3:
        return outcome, verdict, 0
    padded = np.pad(count.astype(float), _AROUND, constant_values=np.nan)
    window = np.lib.stride_tricks.sliding_window_view(padded, 2 * _AROUND + 1)
    around = np.nanmedian(np.delete(window, _AROUND, axis=1), axis=1)
    sparse = (count <= MIN_OWN_BBS) & (around >= count + 2)
    if not sparse.any():
        return outcome, verdict, 0
    solved = (quality.status == OWN) & ~sparse
    filled = fill_states(ViewState(np.nan_to_num(state.R), np.nan_to_num(state.t), state.k), solved, len(solved))
    again = assign_by_pose(cands, model, filled, outcome[1], tset)
    # where frames jump farther than the BBs lie apart, a neighbour's pose misplaces them all; the view's own
    # three or four BBs, its pose fitted to them from the neighbour's, place the ones it lost. Per view, the
    # prediction that finds more BBs
    idx = np.flatnonzero(sparse & (count >= 3))
    if idx.size:
        sub = ViewModel(model.nominal[idx], model.intrinsics)
        fitted = fit_rigid_poses(sub, ViewState(filled.R[idx], filled.t[idx], filled.k[idx]), outcome[1], uv[idx])
        own = ViewState(filled.R.copy(), filled.t.copy(), filled.k.copy())
        own.R[idx], own.t[idx] = fitted.R, fitted.t
        by_own = assign_by_pose(cands, model, own, outcome[1], tset)
        better = np.zeros(len(count), bool)
        better[idx] = all_finite(by_own[idx]).sum(1) > all_finite(again[idx]).sum(1)
        again = np.where(better[:, None, None], by_own, again)
    gain = sparse & (all_finite(again).sum(1) > count)
    if not gain.any():
        return outcome, verdict, 0
    new = uv.copy()
    new[gain] = again[gain]
    outcome, verdict, kept = estimate_again(model, new, proj, opt, progress, outcome, verdict)
    return outcome, verdict, int(gain.sum()) if kept else 0


def jumped_views_again(
    cands: list[NDArray[np.float64]],
    model: ViewModel,
    tset: TrackingSettings,
    outcome: tuple[Any, ...],
    verdict: CalibrationVerdict,
    proj: NDArray[np.intp],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
) -> tuple[tuple[Any, ...], CalibrationVerdict, int]:
    """Views not calibrated from their own BBs whose frame jumped farther than the BBs lie apart (an orbit many
    times the bench profile's errors: a neighbour's pose puts no BB on its own blob): each is placed by the 2-D
    similarity that carries the most BBs onto blobs (:func:`calib.identify.placed_by_similarity`), its BBs assigned
    through the pose fitted to them, and the geometry estimated again with the views that gain BBs; kept unless
    worse. Also how many views gained."""
    state, xyz, uv, quality = outcome[2], outcome[1], outcome[3], outcome[7]
    solved = quality.status == OWN
    views = np.flatnonzero(~solved)
    if not solved.any() or not len(views):
        return outcome, verdict, 0
    known = ViewState(np.nan_to_num(state.R), np.nan_to_num(state.t), state.k)
    guesses = [fill_states(known, solved, len(solved)), *neighbour_states(known, solved), model.identity()]
    placed = placed_by_similarity(cands, model, guesses, xyz, tset, views)
    # the placed poses are fitted to the BBs: no frame shift left to search for
    again = assign_by_pose(cands, model, placed, xyz, replace(tset, jitter_px=0.0))
    count = all_finite(uv).sum(1)
    gain = np.zeros(len(count), bool)
    gain[views] = (all_finite(again[views]).sum(1) >= MIN_OWN_BBS) & (all_finite(again[views]).sum(1) > count[views])
    if not gain.any():
        return outcome, verdict, 0
    new = uv.copy()
    new[gain] = again[gain]
    outcome, verdict, kept = estimate_again(model, new, proj, opt, progress, outcome, verdict)
    return outcome, verdict, int(gain.sum()) if kept else 0


def mild_misfits_only(quality: ViewQuality, verdict: CalibrationVerdict) -> bool:
    """Whether the only reason a result failed is a few views with enough BBs whose residual exceeds the misfit
    limit by less than half again (centroid biases, not a BB taken for another, which leaves pixels): tracking
    again with larger jumps cannot change that, so the recovery stops (the verdict still fails)."""
    odd = quality.inconsistent
    if len(verdict.reasons) != 1 or not odd.any() or ((quality.status == FAILED) & ~odd).any():
        return False
    return float(np.nanmax(quality.misfit_px[odd])) < 1.5 * misfit_limit_px(quality.noise_px)


def split_merged(
    target: Path,
    proj: NDArray[np.intp],
    model: ViewModel,
    outcome: tuple[Any, ...],
    verdict: CalibrationVerdict,
    d_px: float,
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
) -> tuple[tuple[Any, ...], CalibrationVerdict, int]:
    """Views where two BBs project onto one blob (both left out by the assignment): their two centroids fitted
    in the frame (:mod:`calib.split`), then the geometry estimated again; kept when the result is no worse.
    Also the number of blobs split. Only when such blobs are at least :data:`SPLIT_MIN_SHARE` of the detections:
    BBs that cross now and then change nothing measurable (experiment A at 768 px: 17 blobs among 4000
    detections, 0.129 px either way) but the fits and the second estimate would cost 0.3 s."""
    geometry_p, xyz, uv = outcome[0], outcome[1], outcome[3]
    with np.errstate(invalid="ignore"):
        predicted = geometry_p.project(xyz)
    s = SplitSettings(diameter_px=d_px, max_shift_px=max(2.0, 0.5 * d_px))
    pairs = merged_pairs(predicted, uv, TrackingSettings(diameter_px=d_px).overlap_factor * d_px)
    if len(pairs) < SPLIT_MIN_SHARE * all_finite(uv).sum():
        return outcome, verdict, 0
    report(progress, "split", 0, len(pairs), "blobs of two BBs")
    new = uv.copy()
    n_split = 0
    with ScanFile(target) as sf:
        defects = sf.defects()  # dead pixels and columns filled from their row neighbours, as detection does
        dark, flat = (defects.filled(a) for a in sf.dark_flat())
        den = np.maximum(flat - dark, 1.0).astype(np.float32)
        for p in sorted({v for v, _, _ in pairs}):
            frame = FrameWindows(defects.filled(np.asarray(sf.frames[int(proj[p])])), dark, den)
            profile = radial_profile(frame, uv[p, isolated(predicted[p], uv[p], 2.0 * d_px + 4.0)], s.radius_px)
            if profile is None:
                continue
            for _, j, k in (q for q in pairs if q[0] == p):
                guess = predicted[p, [j, k]]
                fit = fit_pair(frame, guess, profile, s)
                if fit is not None and fit.trusted(guess, s):
                    new[p, [j, k]] = fit.uv
                    n_split += 1
    report(progress, "split", len(pairs), len(pairs), f"{n_split} split")
    if n_split == 0:
        return outcome, verdict, 0
    outcome, verdict, kept = estimate_again(model, new, proj, opt, progress, outcome, verdict)
    return outcome, verdict, n_split if kept else 0


def _leave_one_out_outliers(
    model: ViewModel, state: ViewState, xyz: NDArray[np.float64], uv: NDArray[np.float64], tol_px: float
) -> NDArray[np.bool_]:
    """Per view with 4 or more BBs, the detection whose residual, with the view's pose refitted without it,
    is largest and above ``tol_px``."""
    n, k = uv.shape[:2]
    seen = all_finite(uv)
    views = np.flatnonzero(seen.sum(1) >= 5)  # with 4, the pose refitted on 3 has no redundancy to judge by
    out = np.zeros((n, k), bool)
    if views.size == 0:
        return out
    rep_v = np.repeat(views, k)
    rep_k = np.tile(np.arange(k), views.size)
    keep = seen[rep_v, rep_k]
    rep_v, rep_k = rep_v[keep], rep_k[keep]
    sub = ViewModel(model.nominal[rep_v], model.intrinsics)
    obs = uv[rep_v].copy()
    obs[np.arange(len(rep_v)), rep_k] = np.nan  # all left-out problems at once
    st = fit_rigid_poses(sub, ViewState(state.R[rep_v], state.t[rep_v], state.k[rep_v]), xyz, obs, iterations=4)
    pred = sub.project(st, xyz)
    loo = np.linalg.norm(pred[np.arange(len(rep_v)), rep_k] - uv[rep_v, rep_k], axis=-1)
    worst = np.full((n, k), -1.0)
    worst[rep_v, rep_k] = loo
    kmax = worst.argmax(1)
    flag = worst[np.arange(n), kmax] > tol_px
    out[np.flatnonzero(flag), kmax[flag]] = True
    return out


def _drop_single_misfits(
    model: ViewModel,
    state: ViewState,
    xyz: NDArray[np.float64],
    uv: NDArray[np.float64],
    quality: ViewQuality,
    min_own_bbs: int,
) -> tuple[ViewState, NDArray[np.float64], int]:
    """Views that failed only because one detection disagrees with the rest (a biased centroid, a BB taken for
    another): without that detection, and with the pose refitted to the others, they fit within the misfit limit
    and still see ``min_own_bbs`` BBs. Returns the states and detections with those views mended, and how many."""
    limit = misfit_limit_px(quality.noise_px)
    views = np.flatnonzero(quality.inconsistent & (quality.n_bbs >= max(min_own_bbs + 2, 6)))  # 5+ BBs stay
    if views.size == 0:
        return state, uv, 0
    sub = ViewModel(model.nominal[views], model.intrinsics)
    st = ViewState(state.R[views], state.t[views], state.k[views])
    worst = _leave_one_out_outliers(sub, st, xyz, uv[views], 0.0)
    trial = uv[views].copy()
    trial[worst] = np.nan
    refit = fit_rigid_poses(sub, st, xyz, trial, iterations=4)
    mended = np.nan_to_num(view_misfit_px(sub, refit, xyz, trial), nan=np.inf) <= limit
    if not mended.any():
        return state, uv, 0
    idx = views[mended]
    uv = uv.copy()
    uv[idx] = trial[mended]
    R, t, k = state.R.copy(), state.t.copy(), state.k.copy()
    R[idx], t[idx], k[idx] = refit.R[mended], refit.t[mended], refit.k[mended]
    return ViewState(R, t, k), uv, int(idx.size)


def _disagree_with_neighbour(
    model: ViewModel,
    state: ViewState,
    xyz: NDArray[np.float64],
    uv: NDArray[np.float64],
    tol_px: float,
    max_bbs: int = 3,
) -> NDArray[np.bool_]:
    """Detections in views seeing at most ``max_bbs`` BBs that lie more than ``tol_px`` from where the previous
    (or next) view's geometry puts them, after removing the common shift of the view. Views with exactly
    :data:`MIN_OWN_BBS` (one pose to spare) are judged against how far detections in views seeing six or more
    BBs lie from their neighbour's: more than twice that distribution's 99th percentile."""
    n = uv.shape[0]
    count = all_finite(uv).sum(1)
    few = count <= max_bbs
    if n < 2 or not few.any():
        return np.zeros(uv.shape[:2], bool)
    nb = np.where(np.arange(n) > 0, np.arange(n) - 1, 1)
    guess = model.project(ViewState(state.R[nb], state.t[nb], state.k[nb]), xyz)
    d = uv - guess
    with np.errstate(invalid="ignore"):
        shift = np.nanmedian(d, axis=1, keepdims=True)
        off = np.linalg.norm(d - shift, axis=-1)
    tol = np.full(n, tol_px)
    ref = off[(count >= 6)[:, None] & np.isfinite(off)]
    if ref.size:  # the orbit's own frame-to-frame changes beyond a common shift (a wide panel sees rotations)
        tol[count == MIN_OWN_BBS] = max(tol_px, 2.0 * float(np.quantile(ref, 0.99)))
    with np.errstate(invalid="ignore"):
        return (off > tol[:, None]) & few[:, None] & all_finite(uv)


History = list[tuple[NDArray[np.float64], NDArray[np.float64]]]


class Polish(NamedTuple):
    """Solve once more from ``start``, a previous outcome of :func:`estimate` on the same detections, each residual
    divided by ``spread_of(uv)``: the detection's expected error relative to the others for detections ``(N, K, 2)``."""

    start: tuple[Any, ...]
    spread_of: Callable[[NDArray[np.float64]], NDArray[np.float64]]


def min_observations(opt: CalibrationOptions, n_projections: int) -> int:
    """Frames a BB must be seen in: ``opt.min_observations``, by default 5 % of the projections and at least 8."""
    return opt.min_observations or max(8, int(0.05 * n_projections))


def _free_parameters(sub: ViewModel, xyz: NDArray[np.float64]) -> int:
    """What a bundle solve of the views ``sub`` and BB centres ``xyz`` fits: every view's parameters and every
    centre, less the seven of the similarity gauge (the centroid noise's degrees of freedom)."""
    return sub.n_params * sub.nominal.n_views + 3 * xyz.shape[0] - 7


def polished(
    sub: ViewModel,
    uvs: NDArray[np.float64],
    start: tuple[Any, ...],
    ok: NDArray[np.bool_],
    placed: NDArray[np.bool_],
    spread: NDArray[np.float64],
    opt: CalibrationOptions,
    iters: int,
    record: Callable[[ViewState, NDArray[np.float64]], None],
) -> tuple[ViewState, NDArray[np.float64]]:
    """One bundle solve of the views ``sub`` (rows ``ok`` of all views) from a previous outcome of
    :func:`estimate` ``start`` (its failed views from their nominal pose), with the Huber threshold fitted to that
    estimate's residuals."""
    full, xyz0 = start[2], start[1][placed]
    R = np.where(np.isfinite(full.R[ok]).all((1, 2))[:, None, None], full.R[ok], np.eye(3))
    st0 = ViewState(R, np.nan_to_num(full.t[ok]), full.k[ok])
    loss = opt.loss_scale_px
    if loss is None:
        resid = sub.geometry(st0).project(xyz0) - uvs
        loss = huber_threshold_px(centroid_noise_px(resid, _free_parameters(sub, xyz0)))
    res = bundle_adjust(sub, uvs, xyz0, st0, loss_scale_px=loss, max_iterations=iters, gauge_xyz=xyz0, spread=spread)
    record(res.state, res.xyz)
    return res.state, res.xyz


def estimate(
    method: str,
    model: ViewModel,
    uv: NDArray[np.float64],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    polish: Polish | None = None,
) -> tuple[ViewGeometry, NDArray[np.float64], ViewState, NDArray[np.float64], History, int, list[str], ViewQuality]:
    """Geometry of the projection views (NaN where failed), BB centres, states, cleaned uv, history, quality.
    With ``polish`` (its previous outcome from these detections, already cleaned of wrong blobs): one bundle solve
    from that solution instead of the first solve and its checks, its history and warnings continued, each residual
    divided by the detection's spread."""
    warnings: list[str] = []
    n = uv.shape[0]
    ok = usable_views(uv, opt.min_bbs_per_view)
    # a BB seen in fewer of the solved views than identification asks for is not placed: a few views far apart fit
    # any pairing of blobs, and views resting on such BBs calibrate as an island of their own, tens of px off
    min_obs = min_observations(opt, n)
    placed = all_finite(uv[ok]).sum(0) >= min_obs
    if not placed.all():
        warnings.append(
            f"{int((~placed).sum())} BB(s) seen in fewer than {min_obs} of the views to solve were left out "
            "(too few views to place them)"
        )
        uv = uv[:, placed]
        ok = usable_views(uv, opt.min_bbs_per_view)
    if ok.sum() < 2:
        raise NoMarkersError(
            f"only {int(ok.sum())} view(s) see {opt.min_bbs_per_view} or more BBs; nothing to calibrate"
        )
    sub = ViewModel(model.nominal[np.flatnonzero(ok)], model.intrinsics)
    uvs = uv[ok]
    history: History = []

    def record(state: ViewState, xyz: NDArray[np.float64]) -> None:
        g = sub.geometry(state)
        rpe = np.full(n, np.nan)
        rpe[ok] = rpe_per_frame(g, uvs, xyz)
        res = np.full(uv.shape[:2], np.nan)
        res[ok] = residual_px(g, uvs, xyz)
        history.append((rpe, res))
        last = history[-1][0]
        report(progress, "estimate", len(history) - 1, iters, "", rpe_mean_mm=float(np.nanmean(last)))

    if method == "paper":
        iters = opt.iterations or 3
        state, xyz = paper_calibrate(sub, uvs, iterations=iters, callback=lambda i, s, x: record(s, x))
        n_iter = iters
    elif polish is not None:
        iters = opt.iterations or 30
        history.extend(polish.start[4])
        warnings.extend(polish.start[6])
        state, xyz = polished(sub, uvs, polish.start, ok, placed, polish.spread_of(uv)[ok], opt, iters, record)
        n_iter = len(history) - 1
    else:
        iters = opt.iterations or 30
        xyz0 = triangulate_least_squares(*marker_rays(sub.nominal, uvs))
        record(sub.identity(), xyz0)
        res = bundle_adjust(
            sub,
            uvs,
            xyz0,
            loss_scale_px=opt.loss_scale_px or FIRST_LOSS_SCALE_PX,
            max_iterations=iters,
            callback=lambda i, s, x, c: record(s, x),
        )
        # detections far off the solution are wrong blobs: drop them and refine once more
        r = residual_px(sub.geometry(res.state), uvs, res.xyz)
        fin = np.isfinite(r)
        sigma = 1.4826 * float(np.median(r[fin])) if fin.any() else 0.0
        bad = fin & (r > max(opt.outlier_px, 6.0 * sigma))
        n_bad = int(bad.sum())
        if n_bad:
            warnings.append(f"{n_bad} detection(s) off by more than {max(opt.outlier_px, 6 * sigma):.2f} px set to NaN")
        # a pose absorbs much of one wrong blob: test each detection against the pose fitted without it, and
        # views left with 4 BBs or fewer (too little redundancy to tell a wrong one) against the neighbouring
        # view: two wrong blobs among four can fit a wrong pose closely (experiment C at 512 px: 7 px off)
        bad |= _leave_one_out_outliers(
            sub, res.state, res.xyz, np.where(bad[..., None], np.nan, uvs), 1.5 * opt.outlier_px
        )
        bad |= _disagree_with_neighbour(
            sub, res.state, res.xyz, np.where(bad[..., None], np.nan, uvs), 3.0 * opt.outlier_px, max_bbs=MIN_OWN_BBS
        )
        if bad.sum() > n_bad:
            warnings.append(
                f"{int(bad.sum()) - n_bad} detection(s) disagree with their view fitted without them (or, "
                f"with {MIN_OWN_BBS} BBs or fewer, with the neighbouring view); set to NaN"
            )
        loss = opt.loss_scale_px
        if loss is None:  # the robust loss fitted to this scan's centroid noise, measured on the first solution
            clean = np.where(bad[..., None], np.nan, sub.geometry(res.state).project(res.xyz) - uvs)
            sigma = centroid_noise_px(clean, _free_parameters(sub, res.xyz))
            loss = huber_threshold_px(sigma)
        if bad.any() or loss != FIRST_LOSS_SCALE_PX:
            uvs = uvs.copy()
            uvs[bad] = np.nan
            uv = uv.copy()
            uv[ok] = uvs
            res = bundle_adjust(sub, uvs, res.xyz, res.state, loss_scale_px=loss, max_iterations=iters, gauge_xyz=xyz0)
            record(res.state, res.xyz)
        state, xyz = res.state, res.xyz
        n_iter = len(history) - 1
    full_state = ViewState.identity(n, model.n_intrinsics)
    full_state.R[ok], full_state.t[ok], full_state.k[ok] = state.R, state.t, state.k
    uv = uv.copy()
    uv[ok] = uvs
    in_bundle = np.zeros(n, bool)
    in_bundle[np.flatnonzero(ok)[usable_views(uvs, opt.min_bbs_per_view)]] = True
    if (~in_bundle).any() and in_bundle.any():
        # views outside the adjustment: keep only detections that agree with the neighbouring views' geometry
        guess = model.project(fill_states(full_state, in_bundle, n), xyz)
        off = (np.linalg.norm(guess - uv, axis=-1) > 3.0 * opt.outlier_px) & ~in_bundle[:, None]
        if off.any():
            uv[off] = np.nan
            warnings.append(
                f"{int(off.sum())} detection(s) in views outside the adjustment disagree with their "
                "neighbours and were set to NaN"
            )
    resid_xy = sub.geometry(state).project(xyz) - uvs
    noise = centroid_noise_px(resid_xy, _free_parameters(sub, xyz))
    paper = method == "paper"
    min_own = opt.min_bbs_per_view if paper else max(MIN_OWN_BBS, opt.min_bbs_per_view)
    fitted_state = full_state
    full_state, quality = assess_views(
        model, fitted_state, xyz, uv, noise_px=noise, min_own_bbs=min_own, max_gap=0 if paper else opt.bridge_max_views
    )
    if not paper and quality.inconsistent.any():
        fitted_state, uv, n_mended = _drop_single_misfits(model, fitted_state, xyz, uv, quality, min_own)
        if n_mended:
            warnings.append(
                f"{n_mended} view(s) fitted only without one detection that disagreed with the rest of "
                "the view; that detection was set to NaN"
            )
            full_state, quality = assess_views(
                model, fitted_state, xyz, uv, noise_px=noise, min_own_bbs=min_own, max_gap=opt.bridge_max_views
            )
    if quality.counts()["own"] == 0:
        raise NoMarkersError(
            f"no view sees the {MIN_OWN_BBS if not paper else opt.min_bbs_per_view} BBs it needs to be calibrated (and "
            f"checked) on its own: at most {int(quality.n_bbs.max(initial=0))} BBs per view; a pose fitted to 3 BBs "
            "has no redundancy and cannot be trusted. Tape more BBs on the object (6 to 10 are recommended)."
        )
    vec = model.geometry(
        ViewState(np.nan_to_num(full_state.R), np.nan_to_num(full_state.t), full_state.k)
    ).vectors.copy()
    vec[quality.status == FAILED] = np.nan
    return model.nominal.with_vectors(vec), xyz, full_state, uv, history, n_iter, warnings, quality
