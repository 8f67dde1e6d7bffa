"""From per-frame candidates to marker centroids ``(P, K, 2)`` with one identity per BB (see ``track.py``)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from calib.bundle import bundle_adjust
from calib.detect import N_FIELDS
from calib.model import ViewModel, ViewState, all_finite
from calib.quality import fit_rigid_poses
from calib.rays import marker_rays, triangulate_least_squares
from calib.track import TrackingSettings, assign_to_predictions, ball_like, like_the_others, link_fragments
from orbitct.geometry import Panel, ViewGeometry
from orbitct.rotations import similarity_fit


def usable_views(uv: NDArray[np.float64], min_bbs: int) -> NDArray[np.bool_]:
    """Views that see at least ``min_bbs`` markers."""
    return all_finite(uv).sum(1) >= min_bbs


def fill_states(state: ViewState, solved: NDArray[np.bool_], n: int) -> ViewState:
    """States for all ``n`` views: solved ones as given, others copied from the nearest solved view."""
    idx = np.flatnonzero(solved)
    nearest = idx[np.clip(np.searchsorted(idx, np.arange(n)), 0, len(idx) - 1)]
    left = idx[np.clip(np.searchsorted(idx, np.arange(n)) - 1, 0, len(idx) - 1)]
    nearest = np.where(np.abs(left - np.arange(n)) < np.abs(nearest - np.arange(n)), left, nearest)
    return ViewState(state.R[nearest], state.t[nearest], state.k[nearest])


def neighbour_states(state: ViewState, solved: NDArray[np.bool_]) -> tuple[ViewState, ViewState]:
    """States for all views copied from the nearest solved view before each, and after each (the first or last
    solved one where there is none on that side)."""
    idx = np.flatnonzero(solved)
    at = np.searchsorted(idx, np.arange(len(solved)))
    before = idx[np.clip(at - 1, 0, len(idx) - 1)]
    after = idx[np.clip(np.searchsorted(idx, np.arange(len(solved)), side="right"), 0, len(idx) - 1)]
    return (
        ViewState(state.R[before], state.t[before], state.k[before]),
        ViewState(state.R[after], state.t[after], state.k[after]),
    )


#: a rough solve's pull of each BB centre towards its first triangulation (standard deviation): weak enough to leave
#: every centre the views hold where they put it, strong enough that one they hold poorly cannot run away
ROUGH_POINT_PRIOR_MM = 1000.0


def rough_solve(
    model: ViewModel, uv: NDArray[np.float64], min_bbs: int = 3, iterations: int = 8, prior_scale: float = 1.0
) -> tuple[ViewState, NDArray[np.float64], NDArray[np.bool_]]:
    """Quick robust bundle adjustment on the views that see enough markers; states for every view."""
    ok_views = usable_views(uv, min_bbs)
    sub = ViewModel(model.nominal[np.flatnonzero(ok_views)], "fixed")
    uvs = uv[ok_views]
    xyz0 = triangulate_least_squares(*marker_rays(sub.nominal, uvs))
    bad = ~np.isfinite(xyz0).all(1) | (np.linalg.norm(np.nan_to_num(xyz0, nan=1e9), axis=1) > 5000.0)
    if bad.any():  # tracks seen along nearly one ray: no point to solve for
        uvs = uvs.copy()
        uvs[:, bad] = np.nan
        xyz0[bad] = 0.0
    # the weak pull towards the nominal poses holds parts of the orbit that share no BB track together
    res = bundle_adjust(
        sub,
        uvs,
        xyz0,
        loss_scale_px=2.0,
        max_iterations=iterations,
        pose_prior=(0.05 * prior_scale, 20.0 * prior_scale),
        point_prior_mm=ROUGH_POINT_PRIOR_MM,
    )
    full = ViewState.identity(model.nominal.n_views, 0)
    full.R[ok_views], full.t[ok_views] = res.state.R, res.state.t
    return fill_states(full, ok_views, model.nominal.n_views), res.xyz, ok_views


def _fit_rms(geometry: ViewGeometry, uv: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Triangulated points ``(K,3)`` of tracks ``(N,K,2)`` and their RMS reprojection error (px)."""
    xyz = triangulate_least_squares(*marker_rays(geometry, uv))
    err = np.linalg.norm(geometry.project(xyz) - uv, axis=-1)
    seen = np.isfinite(err)
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(np.where(seen, err**2, 0.0).sum(0) / seen.sum(0))
    return xyz, rms


def merge_fragments(
    frags: NDArray[np.float64], geometry: ViewGeometry, xyz: NDArray[np.float64], tol_px: float, near_mm: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Join fragments that never share a frame, lie within ``near_mm`` of each other (rough centres ``xyz``)
    and fit one 3-D point together within ``tol_px`` RMS (greedy, best pair first).
    Returns the merged tracks and their RMS reprojection error through ``geometry``.

    The fit of a union is computed from additive sums over its rays (normal equations of the
    least-squares ray intersection), with the ray distance converted to pixels at the mean magnification."""
    n, f = frags.shape[:2]
    origin, direction = marker_rays(geometry, frags)
    seen = all_finite(direction)
    d = np.where(seen[..., None], direction, 0.0)
    o = np.where(seen[..., None], origin, 0.0)
    cnt = seen.sum(0).astype(float)
    dt = np.ascontiguousarray(d.transpose(1, 2, 0))  # (F,3,N)
    A = cnt[:, None, None] * np.eye(3) - dt @ np.ascontiguousarray(d.transpose(1, 0, 2))  # sum of I - d d^T
    od = (o * d).sum(-1)  # (N,F)
    b = o.sum(0) - (d * od[..., None]).sum(0)
    c = (o * o).sum((0, 2)) - (od**2).sum(0)
    mm_per_px = 1.0 / float(np.median(geometry[geometry.valid].projected_size_px(1.0)))
    tol_mm = tol_px * mm_per_px
    groups = [[j] for j in range(f)]
    alive = np.ones(f, bool)
    centres = xyz.copy()
    vis = seen.T.astype(np.float32)
    share_all = (vis @ vis.T) > 0  # (F,F): fragments seen together in some frame
    while True:
        idx = np.flatnonzero(alive)
        C = centres[idx]
        near = np.linalg.norm(C[:, None] - C[None], axis=-1) < near_mm
        shared = share_all[np.ix_(idx, idx)]
        ia, ib = np.nonzero(np.triu(near & ~shared, 1))
        if ia.size == 0:
            break
        a, bb = idx[ia], idx[ib]
        Au, bu, cu, nu = A[a] + A[bb], b[a] + b[bb], c[a] + c[bb], cnt[a] + cnt[bb]
        x = np.linalg.solve(Au + 1e-9 * np.eye(3), bu[..., None])[..., 0]
        ss = np.einsum("pi,pij,pj->p", x, Au, x) - 2 * np.einsum("pi,pi->p", bu, x) + cu
        rms = np.sqrt(np.maximum(ss, 0.0) / np.maximum(nu, 1.0))
        good = rms < tol_mm
        if not good.any():
            break
        best = int(np.flatnonzero(good)[np.argmin(rms[good])])
        p, q = int(a[best]), int(bb[best])
        A[p], b[p], c[p], cnt[p], centres[p] = Au[best], bu[best], cu[best], nu[best], x[best]
        share_all[p] |= share_all[q]
        share_all[:, p] = share_all[p]
        groups[p] += groups[q]
        alive[q] = False
    tracks = []
    for j in np.flatnonzero(alive):
        t = np.full((n, 2), np.nan)
        for m in groups[j]:
            t = np.where(np.isfinite(t), t, frags[:, m])
        tracks.append(t)
    stack = np.stack(tracks, 1)
    return stack, _fit_rms(geometry, stack)[1]


def _join_across(frags: NDArray[np.float64], geometry: ViewGeometry, near_mm: float) -> NDArray[np.float64]:
    """Join tracks that never share a frame and are each other's nearest neighbour in 3-D within ``near_mm``
    (parts of an orbit linked only through the nominal geometry).

    Joined tracks have disjoint frames, so the normal equations of their least-squares ray intersection add."""
    f = frags.shape[1]
    if f < 2:
        return frags
    origin, direction = marker_rays(geometry, frags)
    ok = all_finite(direction) & all_finite(origin)
    d = np.where(ok[..., None], direction, 0.0)
    o = np.where(ok[..., None], origin, 0.0)
    cnt = ok.sum(0)
    dk = np.ascontiguousarray(d.transpose(1, 2, 0))  # (F, 3, N)
    A = cnt[:, None, None] * np.eye(3) - dk @ np.ascontiguousarray(d.transpose(1, 0, 2))
    b = o.sum(0) - (dk @ (o * d).sum(-1).T[..., None])[..., 0]
    vis = np.isfinite(frags[..., 0]).T.astype(np.int32)
    share_all = (vis @ vis.T) > 0
    members = [[j] for j in range(f)]
    alive = list(range(f))
    while len(alive) > 1:
        idx = np.array(alive)
        xyz = np.full((idx.size, 3), np.nan)
        good = cnt[idx] >= 2
        if good.any():
            xyz[good] = np.linalg.solve(A[idx[good]], b[idx[good]][..., None])[..., 0]
        dist = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
        dist[~np.isfinite(dist)] = np.inf
        np.fill_diagonal(dist, np.inf)
        share = share_all[np.ix_(idx, idx)]
        nearest = dist.argmin(1)
        cand = [
            (dist[i, j], i, j)
            for i, j in enumerate(nearest)
            if i < j and nearest[j] == i and dist[i, j] < near_mm and not share[i, j]
        ]
        if not cand:
            break
        _, i, j = min(cand)
        p, q = int(idx[i]), int(idx[j])
        A[p] += A[q]
        b[p] += b[q]
        cnt[p] += cnt[q]
        share_all[p] |= share_all[q]
        share_all[:, p] = share_all[p]
        members[p] += members[q]
        alive.remove(q)
    out = np.full((frags.shape[0], len(alive), 2), np.nan)
    for col, j in enumerate(alive):
        for m in members[j]:
            out[:, col] = np.where(np.isfinite(out[:, col]), out[:, col], frags[:, m])
    return out


def _seen_apart(uv: NDArray[np.float64]) -> NDArray[np.bool_]:
    """``(K, K)``: whether two BBs of ``uv`` are (almost) never seen in the same frame — in fewer than 3 frames or
    a tenth of the frames of the one seen less: pieces of one BB's track, never two BBs."""
    seen = all_finite(uv)
    count = seen.sum(0)
    together = seen.T.astype(np.int32) @ seen.astype(np.int32)
    return together < np.maximum(3, 0.1 * np.minimum(count[:, None], count[None]))


def merge_duplicates(
    xyz: NDArray[np.float64], uv: NDArray[np.float64], diameter_mm: float, near_diameters: float = 2.0
) -> NDArray[np.float64]:
    """3-D points ``(K,3)`` with duplicates of one BB removed, keeping the one seen in more frames of ``uv``.

    Two points are one BB when they lie closer than most of a BB diameter (two balls cannot overlap), or
    closer than ``near_diameters`` diameters while their tracks are (almost) never seen in the same frame
    (pieces of one BB's track that a rough geometry placed apart). Two real BBs that close are seen
    together: both are kept, and views where their projections overlap are left out later."""
    count = all_finite(uv).sum(0)
    apart = _seen_apart(uv)
    alive = np.ones(len(xyz), bool)
    dist = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    for flat in np.argsort(dist, axis=None):
        a, b = np.unravel_index(flat, dist.shape)
        if dist[a, b] >= near_diameters * diameter_mm:
            break
        if a >= b or not (alive[a] and alive[b]):
            continue
        if dist[a, b] < 0.75 * diameter_mm or apart[a, b]:
            alive[b if count[a] >= count[b] else a] = False
    return xyz[alive]


def twin_constellation(
    xyz: NDArray[np.float64],
    uv: NDArray[np.float64],
    tol_mm: float = 1.0,
    min_pairs: int = 4,
    tries: int = 300,
    seed: int = 0,
) -> list[tuple[int, int]]:
    """Pairs ``(a, b)`` of BB points ``xyz`` (K, 3) that are one BB each, identified twice in two parts of the orbit
    that the rest of the solution does not tie together (frames where tracking broke for every BB at once): each
    pair is (almost) never seen in the same frame of ``uv``, and one similarity maps every ``b`` onto its ``a``
    within ``tol_mm`` — at least ``min_pairs`` of them, which distinct BBs taped at random never do. The points
    seen in more frames are the ``a``; empty when there is no such twin. Triples of pairs whose distances agree
    on one scale are tried (at most ``tries``), each fitted and counted."""
    count = all_finite(uv).sum(0)
    apart = _seen_apart(uv)
    a_idx, b_idx = np.nonzero(apart & (count[:, None] >= count[None]) & ~np.eye(len(xyz), dtype=bool))
    n = a_idx.size
    if n < min_pairs or len(xyz) < 2 * min_pairs:
        return []
    dist = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    da, db = dist[np.ix_(a_idx, a_idx)], dist[np.ix_(b_idx, b_idx)]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = da / db  # one similarity: the same for every two true pairs
        fits = (db > 10.0 * tol_mm) & (np.abs(np.log(ratio)) < 0.1)
    fits &= (a_idx[:, None] != a_idx[None]) & (b_idx[:, None] != b_idx[None]) & (a_idx[:, None] != b_idx[None])
    p, q = np.nonzero(np.triu(fits, 1))
    if p.size == 0:
        return []
    rng = np.random.default_rng(seed)
    best: list[tuple[int, int]] = []
    for i in rng.permutation(p.size)[:tries]:
        r = ratio[p[i], q[i]]
        third = np.flatnonzero(
            fits[p[i]] & fits[q[i]] & (np.abs(ratio[p[i]] / r - 1) < 0.02) & (np.abs(ratio[q[i]] / r - 1) < 0.02)
        )
        if third.size == 0:
            continue
        trio = np.array([p[i], q[i], third[0]])
        s, R, t = similarity_fit(xyz[b_idx[trio]], xyz[a_idx[trio]])
        miss = np.linalg.norm(s * xyz[b_idx] @ R.T + t - xyz[a_idx], axis=1)
        pairs: list[tuple[int, int]] = []
        used: set[int] = set()
        for j in np.argsort(miss):
            if miss[j] >= tol_mm:
                break
            if int(a_idx[j]) not in used and int(b_idx[j]) not in used:
                pairs.append((int(a_idx[j]), int(b_idx[j])))
                used |= {int(a_idx[j]), int(b_idx[j])}
        if len(pairs) > len(best):
            best = pairs
    return best if len(best) >= min_pairs else []


def assign_visible(
    cands: list[NDArray[np.float64]], predicted: NDArray[np.float64], panel: Panel, settings: TrackingSettings
) -> NDArray[np.float64]:
    """Assign candidates to the predicted BB positions ``(P, K, 2)`` that lie wholly on the panel."""
    margin = 0.5 * settings.diameter_px + 1.0
    inside = (
        (predicted[..., 0] >= margin)
        & (predicted[..., 0] <= panel.cols - 1 - margin)
        & (predicted[..., 1] >= margin)
        & (predicted[..., 1] <= panel.rows - 1 - margin)
    )
    return assign_to_predictions(
        cands, np.where(inside[..., None], predicted, np.nan), settings, gate_px=max(2.0, 0.5 * settings.diameter_px)
    )


def assign_by_pose(
    cands: list[NDArray[np.float64]],
    model: ViewModel,
    state: ViewState,
    xyz: NDArray[np.float64],
    settings: TrackingSettings,
    rounds: int = 3,
) -> NDArray[np.float64]:
    """Assign candidates to the BBs ``xyz`` predicted through ``state`` (a guess per view, such as its nearest
    calibrated neighbour), then, per view with four or more matches, fit the view's rigid pose to them and
    assign again through it. A pose follows the parallax of BBs at different depths that a 2-D shift and
    affine map cannot, so large per-view errors still land every BB on its own blob."""
    uv = assign_visible(cands, model.project(state, xyz), model.nominal.panel, settings)
    for _ in range(rounds):
        fit = usable_views(uv, 4)
        if not fit.any():
            break
        idx = np.flatnonzero(fit)
        sub = ViewModel(model.nominal[idx], model.intrinsics)
        st = fit_rigid_poses(sub, ViewState(state.R[idx], state.t[idx], state.k[idx]), xyz, uv[idx])
        state = ViewState(state.R.copy(), state.t.copy(), state.k.copy())
        state.R[idx], state.t[idx] = st.R, st.t
        again = assign_visible(cands, model.project(state, xyz), model.nominal.panel, settings)
        if np.array_equal(again, uv, equal_nan=True):
            break
        uv = again
    return uv


#: a view placed by a 2-D similarity (:func:`placed_by_similarity`) needs this many BBs to agree on it
MIN_PLACING_VOTES = 4
#: how far the 2-D similarity that places a jumped view may turn (rad) and scale the view's guess
PLACING_TURN_RAD = np.radians(20.0)
PLACING_SCALE = (0.8, 1.25)
#: a placed view's pairs fit its pose this well (px), else the pair whose absence fits the others best is left out
PLACING_FIT_PX = 1.0


def placed_by_similarity(
    cands: list[NDArray[np.float64]],
    model: ViewModel,
    guesses: list[ViewState],
    xyz: NDArray[np.float64],
    settings: TrackingSettings,
    views: NDArray[np.intp],
) -> ViewState:
    """Poses for ``views`` whose frame jumped farther from its guesses (states for every view, tried in turn, such
    as its calibrated neighbours on either side) than its BBs lie apart, so that no BB lands on its own blob. Every
    2-D shift that carries a predicted BB onto a ball-like candidate is tried, then, where none gathers enough,
    every 2-D similarity that carries two onto two (turning at most :data:`PLACING_TURN_RAD`, scaling within
    :data:`PLACING_SCALE`); the one that carries the most BBs (at least :data:`MIN_PLACING_VOTES`, each onto a blob
    of its own) within a third of their median spacing is taken, and the view's rigid pose fitted to those pairs
    from that guess, leaving out one pair at a time while they fit worse than :data:`PLACING_FIT_PX`. Views where
    none gathers enough keep the first guess."""
    first = guesses[0]
    out = ViewState(first.R.copy(), first.t.copy(), first.k.copy())
    if not len(views):
        return out
    uv = np.full((len(views), xyz.shape[0], 2), np.nan)
    start = ViewState(first.R[views].copy(), first.t[views].copy(), first.k[views].copy())
    todo = np.ones(len(views), bool)
    for guess in guesses:
        predicted = model.project(guess, xyz)[views]  # (V, K, 2)
        for i in np.flatnonzero(todo):
            c = cands[views[i]]
            c = c[ball_like(c, settings), :2] if len(c) else np.zeros((0, 2))
            found = _similarity_pairs(predicted[i], c)
            if found is not None:
                uv[i, found[0]] = c[found[1]]
                start.R[i], start.t[i], start.k[i] = guess.R[views[i]], guess.t[views[i]], guess.k[views[i]]
                todo[i] = False
    placed = usable_views(uv, MIN_PLACING_VOTES)
    if not placed.any():
        return out
    idx = views[placed]
    sub = ViewModel(model.nominal[idx], model.intrinsics)
    pairs, guess = uv[placed], ViewState(start.R[placed], start.t[placed], start.k[placed])
    fitted = fit_rigid_poses(sub, guess, xyz, pairs)
    for _ in range(xyz.shape[0]):  # a blob near a BB may have been paired with it: leave out the pair whose
        # absence fits the others best, while the view's pairs fit worse than PLACING_FIT_PX
        worst = _worst_fit_px(sub, fitted, xyz, pairs)
        bad = np.flatnonzero((worst > PLACING_FIT_PX) & (all_finite(pairs).sum(1) > MIN_PLACING_VOTES))
        if not len(bad):
            break
        b_sub = ViewModel(sub.nominal[bad], model.intrinsics)
        b_guess = ViewState(guess.R[bad], guess.t[bad], guess.k[bad])
        without = np.full((len(bad), xyz.shape[0]), np.inf)
        for j in range(xyz.shape[0]):
            trial = pairs[bad].copy()
            trial[:, j] = np.nan
            has = all_finite(pairs[bad, j])
            if has.any():
                st = fit_rigid_poses(b_sub, b_guess, xyz, trial)
                without[has, j] = _worst_fit_px(b_sub, st, xyz, trial)[has]
        pairs[bad, np.argmin(without, axis=1)] = np.nan
        refit = fit_rigid_poses(b_sub, b_guess, xyz, pairs[bad])
        fitted.R[bad], fitted.t[bad] = refit.R, refit.t
    out.R[idx], out.t[idx] = fitted.R, fitted.t
    return out


def _worst_fit_px(
    model: ViewModel, state: ViewState, xyz: NDArray[np.float64], pairs: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Per view, the largest distance (px) between a paired blob and its BB's projection through ``state``."""
    off = np.linalg.norm(model.project(state, xyz) - pairs, axis=-1)
    return np.asarray(np.where(np.isfinite(off), off, 0.0).max(axis=1))


def _similarity_pairs(
    p: NDArray[np.float64], c: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.intp]] | None:
    """The BBs ``p`` (K, 2; NaN: not predicted) and candidates ``c`` (M, 2) that the best 2-D placing pairs
    (:func:`placed_by_similarity`): a shift where one gathers enough, else a similarity; as index arrays, None
    when none pairs enough."""
    keep = np.flatnonzero(all_finite(p))
    if len(keep) < MIN_PLACING_VOTES or len(c) < MIN_PLACING_VOTES:
        return None
    P = p[keep, 0] + 1j * p[keep, 1]
    C = c[:, 0] + 1j * c[:, 1]
    apart = np.abs(P[:, None] - P[None])
    np.fill_diagonal(apart, np.inf)
    gate = max(2.0, float(np.median(apart.min(1))) / 3.0)
    shifted = P[None] + (C[None, :] - P[:, None]).reshape(-1, 1)  # every shift of a BB onto a candidate (H, K)
    found = _best_placing(shifted, C, gate)
    if found is None:
        k1, k2 = np.triu_indices(len(P), 1)
        m1, m2 = np.nonzero(~np.eye(len(C), dtype=bool))
        ratio = (C[m2][None] - C[m1][None]) / (P[k2] - P[k1])[:, None]  # (pairs of BBs, pairs of candidates)
        ok = (np.abs(np.angle(ratio)) <= PLACING_TURN_RAD) & (np.abs(ratio) >= PLACING_SCALE[0])
        a, b = np.nonzero(ok & (np.abs(ratio) <= PLACING_SCALE[1]))
        if not len(a):
            return None
        found = _best_placing(C[m1[b]][:, None] + ratio[a, b][:, None] * (P[None] - P[k1[a]][:, None]), C, gate)
    if found is None:
        return None
    return keep[found[0]], found[1]


def _best_placing(
    moved: NDArray[np.complex128], C: NDArray[np.complex128], gate: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]] | None:
    """Of the placings ``moved`` (H, K) of the BBs, the one that puts the most within ``gate`` of the candidates
    ``C``, each BB on a candidate of its own (at least :data:`MIN_PLACING_VOTES`): BB and candidate indices."""
    close = np.abs(moved[:, :, None] - C[None, None]) <= gate  # (H, K, M)
    votes = np.minimum(close.any(2).sum(1), close.any(1).sum(1))  # BBs that can each have a candidate of their own
    best = int(np.argmax(votes))
    if votes[best] < MIN_PLACING_VOTES:
        return None
    d = np.abs(moved[best][:, None] - C[None])
    rows, cols = linear_sum_assignment(np.where(d <= gate, d, 1e9))
    hit = d[rows, cols] <= gate
    if hit.sum() < MIN_PLACING_VOTES:
        return None
    return rows[hit], cols[hit]


def _stacked(cands: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The candidate records of every frame in one array ``(P, M, fields)``, padded with NaN to the longest."""
    out = np.full((len(cands), max((len(c) for c in cands), default=0), N_FIELDS), np.nan)
    for p, c in enumerate(cands):
        out[p, : len(c)] = c
    return out


def _nearest_candidates(
    table: NDArray[np.float64], predicted: NDArray[np.float64], gate_px: float
) -> NDArray[np.float64]:
    """Per frame and BB, the candidate record of ``table`` (:func:`_stacked`) nearest to ``predicted``
    ``(P, K, 2)`` within ``gate_px``: ``(P, K, fields)`` (NaN: none). For BBs looked for one at a time: the frame
    shift that :func:`assign_visible` allows would let a lone BB take any blob nearby."""
    out = np.full(predicted.shape[:2] + (N_FIELDS,), np.nan)
    if not table.shape[1]:
        return out
    with np.errstate(invalid="ignore"):
        d = np.linalg.norm(table[:, None, :, :2] - predicted[:, :, None], axis=-1)  # (P, K, M)
    d[~np.isfinite(d)] = np.inf
    j = np.argmin(d, axis=-1)
    hit = np.take_along_axis(d, j[..., None], axis=-1)[..., 0] <= gate_px
    p = np.broadcast_to(np.arange(len(table))[:, None], j.shape)
    out[hit] = table[p[hit], j[hit]]
    return out


def recover_missed(
    cands: list[NDArray[np.float64]],
    geometry: ViewGeometry,
    xyz: NDArray[np.float64],
    frags: NDArray[np.float64],
    settings: TrackingSettings,
    min_observations: int,
    diameter_mm: float,
    min_found_share: float = 0.5,
    rounds: int = 25,
) -> NDArray[np.float64]:
    """Centres ``(M, 3)`` of BBs beside ``xyz`` that identification lost: a BB whose 2-D track broke into pieces
    too short to triangulate through the rough first poses (over bone edges and clutter, which blur the
    frame-to-frame links) is dropped as inconsistent and never looked for again. Each piece of track ``frags``
    that no BB of ``xyz`` explains is triangulated through a calibrated ``geometry`` and grown (the nearest
    candidates along its predicted path assigned to it, triangulated again, until it settles). It is kept when it
    fits one point, is found in ``min_found_share`` of the frames that should see it, looks like the BBs of
    ``xyz`` (radius within 20 %, background no more than 2.5 times as rough: not a bone edge or a screw head)
    and lies clear of every BB kept."""
    gate = max(2.0, 0.5 * settings.diameter_px)
    seen = np.isfinite(frags[..., 0])
    projected = geometry.project(xyz)
    table = _stacked(cands)
    known = _nearest_candidates(table, projected, gate)
    if not np.isfinite(known[..., 0]).any():
        return np.zeros((0, 3))
    with np.errstate(invalid="ignore"):
        dist = np.linalg.norm(frags[:, :, None] - projected[:, None], axis=-1)
    near = np.where(np.isfinite(dist), dist, np.inf).min(-1) < max(2.0, settings.diameter_px)
    alone = (seen & ~near).sum(0)
    lonely = (alone >= settings.min_fragment) & (alone >= 0.8 * seen.sum(0))
    kept = [np.asarray(q, float) for q in xyz]
    out: list[NDArray[np.float64]] = []
    tol = max(1.0, 0.35 * settings.diameter_px)
    for f in np.flatnonzero(lonely)[np.argsort(-alone[lonely])]:
        track, point, records = frags[:, f : f + 1], None, None
        for _ in range(rounds):
            point, rms = _fit_rms(geometry, track)
            if not np.isfinite(point).all() or not rms[0] <= tol:
                point = None
                break
            records = _nearest_candidates(table, geometry.project(point), gate)
            grown = records[..., :2]
            if np.array_equal(np.isfinite(grown), np.isfinite(track)):
                break
            track = grown
        if point is None or records is None or any(np.linalg.norm(point[0] - q) < 2.0 * diameter_mm for q in kept):
            continue
        found = int(all_finite(track).sum())
        expected = int(np.isfinite(geometry.project(point)).all(-1).sum())
        if like_the_others(records, known) and found >= max(min_observations, min_found_share * expected):
            out.append(point[0])
            kept.append(point[0])
    return np.array(out).reshape(-1, 3)


def identify(
    cands: list[NDArray[np.float64]],
    nominal_model: ViewModel,
    settings: TrackingSettings,
    diameter_mm: float,
    min_observations: int,
    min_found_share: float = 0.25,
    max_rough_points: int = 40,
    prior_scale: float = 1.0,
    linked: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], list[str]]:
    """Marker centroids ``(P, K, 2)`` over projection views, K found here; and warnings. ``prior_scale`` widens
    the pull of the rough solves towards the nominal poses (orbits far from their nominal). ``linked``: the 2-D
    tracks of :func:`link_fragments` with these settings when they exist already (linked while the scan ran)."""
    warnings: list[str] = []
    frags = link_fragments(cands, settings, nominal_model.nominal) if linked is None else linked
    if frags.shape[1] < 3:
        return np.full((len(cands), frags.shape[1], 2), np.nan), warnings
    geo = ViewModel(nominal_model.nominal, "fixed")
    no_k = np.zeros((len(cands), 0))
    longest = np.argsort(-np.isfinite(frags[..., 0]).sum(0))[:max_rough_points]
    if usable_views(frags[:, longest], 3).sum() < 2:  # no two views share three pieces: nothing to solve
        return np.full((len(cands), 0, 2), np.nan), warnings
    state, _, _ = rough_solve(nominal_model, frags[:, np.sort(longest)], prior_scale=prior_scale)
    rough = geo.geometry(ViewState(state.R, state.t, no_k))
    fxyz = triangulate_least_squares(*marker_rays(rough, frags))
    frags, rms = merge_fragments(frags, rough, fxyz, max(1.5, 0.35 * settings.diameter_px), 15.0)
    good = np.isfinite(rms) & (rms < max(2.0, 0.5 * settings.diameter_px))
    frags = _join_across(frags[:, good], rough, 15.0)
    # short leftovers are clutter (or BB pieces the final assignment recovers); they only weaken the solve
    uv = frags[:, np.isfinite(frags[..., 0]).sum(0) >= max(settings.min_fragment, min_observations // 2)]
    det = nominal_model.nominal.panel
    for _ in range(4):
        if uv.shape[1] < 3 or usable_views(uv, 3).sum() < 2:
            break
        k_before = uv.shape[1]
        state, xyz, _ = rough_solve(nominal_model, uv, prior_scale=prior_scale)
        err = np.linalg.norm(geo.project(ViewState(state.R, state.t, no_k), xyz) - uv, axis=-1)
        with np.errstate(invalid="ignore"):
            med = np.nanmedian(err, axis=0)
        consistent = med < max(1.0, 3.0 * float(np.nanmedian(med)))
        uv, xyz = uv[:, consistent], xyz[consistent]
        xyz = merge_duplicates(xyz, uv, diameter_mm)
        predicted = geo.project(ViewState(state.R, state.t, no_k), xyz)
        uv = assign_visible(cands, predicted, det, settings)
        # a real BB is found in a good share of the frames where it should be visible
        found = all_finite(uv).sum(0)
        expected = all_finite(predicted).sum(0)
        uv = uv[:, (found >= settings.min_fragment) & (found >= min_found_share * expected)]
        if uv.shape[1] == k_before:
            break
    count = all_finite(uv).sum(0)
    keep = count >= min_observations
    if (~keep).any():
        warnings.append(f"dropped {int((~keep).sum())} BB candidate(s) seen in fewer than {min_observations} frames")
    uv = uv[:, keep]
    order = np.argsort(np.nanargmax(all_finite(uv), axis=0) if uv.shape[1] else [])
    return uv[:, order], warnings
