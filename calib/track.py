"""BB identities across frames from per-frame candidates: 2-D tracks, 3-D linking, geometry-guided matching.

1. Candidates that look like a ball (size near the expected BB, round) are linked frame to frame: each
   track predicts its next position (constant velocity), predictions and candidates are assigned
   globally (Hungarian), tracks start and end freely; ambiguous approaches of two tracks coast.
2. Fragments long enough to trust are treated as separate points in a quick bundle adjustment from the
   nominal geometry; fragments whose 3-D centres coincide are one BB.
3. Every BB is predicted in every frame through the geometry of step 2 and assigned to candidates again;
   positions where two BBs overlap, where the blob is distorted or too faint (metal, edge) stay NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from calib.detect import CANDIDATE_FIELDS
from orbitct.geometry import ViewGeometry

COL, ROW, SCORE, AMP, RADIUS, ELONG, BG_RMS = (CANDIDATE_FIELDS.index(f) for f in CANDIDATE_FIELDS[:7])


@dataclass
class TrackingSettings:
    """Tolerances of the tracker (pixels at full resolution unless named otherwise)."""

    diameter_px: float
    motion_px: float = 0.0  # typical largest BB motion between neighbouring frames (from the nominal orbit)
    jitter_px: float = 0.0  # frame-to-frame jitter of the real orbit around the nominal one
    min_radius_ratio: float = 0.55
    max_radius_ratio: float = 1.7
    max_elongation: float = 1.6
    max_gap: int = 4
    min_fragment: int = 5
    overlap_factor: float = 1.25
    max_background_ratio: float = 0.25
    max_radius_ratio_large: float = 1.35  # BBs of 4 px and more: measured radius / expected radius
    max_background_ratio_large: float = 0.15  # background roughness / BB amplitude (metal edges are rough)
    min_amplitude_ratio: float = 0.3

    @property
    def gate_px(self) -> float:
        """How far a detection may lie from its track's prediction once the frame's common shift is removed."""
        return max(2.0, 0.6 * self.diameter_px, 0.75 * self.motion_px)

    @property
    def search_px(self) -> float:
        """How far the common shift of a frame's BBs may be from the track predictions."""
        return self.gate_px + 0.5 * self.motion_px + self.jitter_px


def ball_like(c: NDArray[np.float64], s: TrackingSettings) -> NDArray[np.bool_]:
    """Candidates whose size and roundness fit a projected BB."""
    r = 0.5 * s.diameter_px
    small = s.diameter_px < 4.0  # a few pixels: size and shape are dominated by sampling and blur
    return (
        (c[:, RADIUS] >= (0.3 if small else s.min_radius_ratio) * r)
        & (c[:, RADIUS] <= (s.max_radius_ratio * r + 0.5 if small else s.max_radius_ratio_large * r))
        & (c[:, ELONG] <= (s.max_elongation + 1.5 if small else s.max_elongation))
        & (c[:, BG_RMS] <= (s.max_background_ratio if small else s.max_background_ratio_large) * c[:, AMP])
    )


def _hungarian(pred: NDArray[np.float64], cand: NDArray[np.float64], gate: NDArray[np.float64] | float) -> NDArray[np.intp]:
    """Index of the candidate assigned to each prediction (-1: none within its gate)."""
    out = np.full(len(pred), -1)
    if not len(pred) or not len(cand):
        return out
    cost = np.linalg.norm(pred[:, None] - cand[None], axis=-1)
    cost[~np.isfinite(cost)] = 1e6
    big = cost > np.broadcast_to(np.asarray(gate, float).reshape(-1, 1), cost.shape)
    rows, cols = linear_sum_assignment(np.where(big, 1e6, cost))
    good = ~big[rows, cols]
    out[rows[good]] = cols[good]
    return out


def match_frame(
    pred: NDArray[np.float64], cand: NDArray[np.float64], search_px: float, gate_px: NDArray[np.float64] | float
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Assign candidates ``(M,2)`` to predictions ``(T,2)`` (NaN = not expected) after removing the frame's
    common shift (median nearest-neighbour displacement) and, with 3 or more matches, an affine distortion.
    Returns the assignment (-1 = none) and the aligned predictions."""
    pred = pred.copy()
    vis = np.isfinite(pred).all(1)
    if not vis.any() or not len(cand):
        return np.full(len(pred), -1), pred
    diff = cand[None] - pred[vis][:, None]
    dist = np.linalg.norm(diff, axis=-1)
    near_any = dist.min(0) < search_px + 2.0 * float(np.max(gate_px))
    if not near_any.any():
        return np.full(len(pred), -1), pred
    kept = np.flatnonzero(near_any)
    cand, diff, dist = cand[kept], diff[:, kept], dist[:, kept]
    idx, pred = _match_near(pred, vis, cand, diff, dist, search_px, gate_px)
    return np.where(idx >= 0, kept[np.maximum(idx, 0)], -1), pred


def _match_near(
    pred: NDArray[np.float64],
    vis: NDArray[np.bool_],
    cand: NDArray[np.float64],
    diff: NDArray[np.float64],
    dist: NDArray[np.float64],
    search_px: float,
    gate_px: NDArray[np.float64] | float,
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    nearest = dist.argmin(1)
    near = dist[np.arange(len(nearest)), nearest] < search_px
    if near.any():
        pred[vis] += np.median(diff[np.arange(len(nearest)), nearest][near], axis=0)
    idx = _hungarian(pred, cand, np.asarray(gate_px) * 1.5)
    m = idx >= 0
    if m.sum() >= 6:  # enough matches to also take out an affine distortion, if it helps
        A = np.column_stack([pred[m], np.ones(m.sum())])
        coef, *_ = np.linalg.lstsq(A, cand[idx[m]], rcond=None)
        before = np.median(np.linalg.norm(pred[m] - cand[idx[m]], axis=1))
        after = np.median(np.linalg.norm(A @ coef - cand[idx[m]], axis=1))
        if after < before:
            pred[vis] = np.column_stack([pred[vis], np.ones(vis.sum())]) @ coef
    elif m.any():
        pred[vis] += np.median(cand[idx[m]] - pred[m], axis=0)
    return _hungarian(pred, cand, gate_px), pred


def _predict(nominal: ViewGeometry, tracks: list[dict[int, NDArray[np.float64]]], active: list[int], to: int, window: int = 8) -> NDArray[np.float64]:
    """Predicted positions in frame ``to`` of active tracks: their last few detections triangulated through
    the nominal geometry (one detection: the point of its ray nearest the isocenter), projected into ``to``."""
    t_n = len(active)
    if t_n == 0:
        return np.zeros((0, 2))
    frames = np.full((t_n, window), -1)
    uv = np.full((t_n, window, 2), np.nan)
    for a, t in enumerate(active):
        fs = sorted(tracks[t])[-window:]
        frames[a, : len(fs)] = fs
        uv[a, : len(fs)] = [tracks[t][f] for f in fs]
    ok = frames >= 0
    vec = np.where(ok[..., None], nominal.vectors[np.maximum(frames, 0)], np.nan)
    g = ViewGeometry(vec.reshape(-1, 12), nominal.detector)
    o, d = g.backproject(np.where(ok[..., None], uv, 0.0).reshape(-1, 1, 2))
    o = o.reshape(t_n, window, 3)
    d = np.where(ok[..., None], d.reshape(t_n, window, 3), 0.0)
    o = np.where(ok[..., None], o, 0.0)
    proj = (np.eye(3) - d[..., :, None] * d[..., None, :]) * ok[..., None, None]
    A = proj.sum(1)
    b = np.einsum("twij,twj->ti", proj, o)
    single = ok.sum(1) < 2
    # one ray: its point nearest the isocenter
    A[single] += np.eye(3) * 1e-6
    x = np.linalg.solve(A, b[..., None])[..., 0]
    last = ok.sum(1) - 1
    o1, d1 = o[np.arange(t_n), last], d[np.arange(t_n), last]
    x1 = o1 - np.einsum("ij,ij->i", o1, d1)[:, None] * d1
    x = np.where(single[:, None], x1, x)
    P = nominal.matrices[to]  # cached on the nominal geometry
    h = x @ P[:, :3].T + P[:, 3]
    return h[:, :2] / h[:, 2:3]


def link_fragments(cands: list[NDArray[np.float64]], s: TrackingSettings, nominal: ViewGeometry) -> NDArray[np.float64]:
    """2-D tracks ``(P, F, 2)`` over projections (NaN where a fragment has no detection)."""
    tracks: list[dict[int, NDArray[np.float64]]] = []
    active: list[int] = []
    misses: dict[int, int] = {}
    gate = s.gate_px
    for p, c in enumerate(cands):
        c = c[ball_like(c, s)] if len(c) else c
        last_f = np.array([max(tracks[t]) for t in active], dtype=int)
        pred_a = _predict(nominal, tracks, active, p)
        gates = gate * (1.0 + 0.5 * np.clip(p - last_f - 1, 0, None))
        matched_c = np.zeros(len(c), bool)
        matched_t = np.zeros(len(active), bool)
        if len(active) and len(c):
            idx, _ = match_frame(pred_a, c[:, :2], s.search_px, gates)
            for a in np.flatnonzero(idx >= 0):
                tracks[active[a]][p] = c[idx[a], :2].copy()
                matched_c[idx[a]] = True
                matched_t[a] = True
        still = []
        for a, t in enumerate(active):
            if matched_t[a]:
                misses[t] = 0
                still.append(t)
            else:
                misses[t] = misses.get(t, 0) + 1
                if misses[t] <= s.max_gap:
                    still.append(t)
        for b in np.flatnonzero(~matched_c):
            tracks.append({p: c[b, :2].copy()})
            still.append(len(tracks) - 1)
        active = still
    keep = [t for t in tracks if len(t) >= s.min_fragment]
    out = np.full((len(cands), len(keep), 2), np.nan)
    for f, t in enumerate(keep):
        for p, xy in t.items():
            out[p, f] = xy
    return out


def assign_to_predictions(
    cands: list[NDArray[np.float64]], predicted: NDArray[np.float64], s: TrackingSettings, gate_px: float
) -> NDArray[np.float64]:
    """Per frame, candidates assigned globally to predicted BB positions ``(P, K, 2)``; NaN where none fits,
    where two BBs overlap, or where the blob is distorted or much fainter than the BB usually is."""
    n, k = predicted.shape[:2]
    uv = np.full((n, k, 2), np.nan)
    amp = np.full((n, k), np.nan)
    shaped = np.zeros((n, k), bool)
    for p in range(n):
        c = cands[p]
        pr = predicted[p]
        vis = np.isfinite(pr).all(1)
        if not len(c) or not vis.any():
            continue
        idx, _ = match_frame(np.where(vis[:, None], pr, np.nan), c[:, :2], s.search_px, gate_px)
        rows = np.flatnonzero(idx >= 0)
        cols = idx[rows]
        uv[p, rows] = c[cols, :2]
        amp[p, rows] = c[cols, AMP]
        shaped[p, rows] = ball_like(c[cols], s)
        # overlap: two visible predictions closer than the BB size
        if vis.sum() > 1:
            dd = np.linalg.norm(pr[:, None] - pr[None], axis=-1) + np.eye(k) * 1e9
            dd[~vis] = 1e9
            dd[:, ~vis] = 1e9
            uv[p, dd.min(1) < s.overlap_factor * s.diameter_px] = np.nan
    typical = np.nanmedian(np.where(shaped, amp, np.nan), axis=0)
    faint = amp < s.min_amplitude_ratio * typical[None]
    uv[~shaped | faint] = np.nan
    return uv
