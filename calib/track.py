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

import numba
import numpy as np
from numpy.typing import NDArray

from calib.detect import CANDIDATE_FIELDS, solve3
from calib.model import all_finite
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

    @property
    def residual_px(self) -> float:
        """How far a BB may lie from its prediction once the frame's common shift is removed: rotations and
        magnification changes leave more the larger the allowed jump."""
        return max(1.5 * self.gate_px, 0.25 * self.search_px)

    @property
    def ambiguous_px(self) -> float:
        """Two tracks predicted closer than this could swap BBs: both end there (3-D linking joins the pieces)."""
        return 2.0 * max(self.gate_px, 0.5 * self.residual_px)


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


def like_the_others(records: NDArray[np.float64], others: NDArray[np.float64]) -> bool:
    """Whether blobs ``records`` (one BB's, over frames; NaN rows ignored) look like the BBs of ``others``: median
    radius within 20 % of theirs and a background at most 2.5 times as rough (not a bone edge, a screw head or
    a structure of the object that is round for a few frames)."""
    radius, rough = np.nanmedian(others[..., RADIUS]), np.nanmedian(others[..., BG_RMS])
    return bool(
        abs(np.nanmedian(records[..., RADIUS]) / radius - 1.0) <= 0.2
        and np.nanmedian(records[..., BG_RMS]) <= 2.5 * rough
    )


@numba.njit(cache=True)
def _median(values):  # type: ignore[no-untyped-def]
    """Median of a short 1-D array (NaN if it is empty or holds a NaN), by insertion sort: the same value as
    ``np.median``, which takes seconds to compile on a first run after installing where this takes a fraction."""
    n = values.size
    if n == 0:
        return np.nan
    s = values.copy()
    for i in range(n):
        v = s[i]
        if np.isnan(v):
            return np.nan
        j = i - 1
        while j >= 0 and s[j] > v:
            s[j + 1] = s[j]
            j -= 1
        s[j + 1] = v
    return (s[(n - 1) // 2] + s[n // 2]) / 2 if n % 2 == 0 else s[n // 2]


@numba.njit(cache=True)
def _gated_cost(pred, cand, gate):  # type: ignore[no-untyped-def]
    """Distances ``(T, M)`` with 1e6 where a pair is farther than the row's gate (or not finite), and that mask."""
    t_n, m_n = pred.shape[0], cand.shape[0]
    cost = np.empty((t_n, m_n))
    big = np.empty((t_n, m_n), np.bool_)
    for t in range(t_n):
        for m in range(m_n):
            dx = pred[t, 0] - cand[m, 0]
            dy = pred[t, 1] - cand[m, 1]
            d = np.sqrt(dx * dx + dy * dy)
            if not np.isfinite(d):
                d = 1e6
            far = d > gate[t]
            big[t, m] = far
            cost[t, m] = 1e6 if far else d
    return cost, big


@numba.njit(cache=True)
def _min_cost_assignment(cost):  # type: ignore[no-untyped-def]
    """Column of each row ``(T,)`` in a minimum-cost assignment of a ``(T, M)`` matrix (-1: row left over when
    T > M); shortest augmenting paths with potentials (Hungarian method), for the small matrices of one frame."""
    t_n, m_n = cost.shape
    flip = t_n > m_n
    c = cost.T.copy() if flip else cost
    n, m = c.shape
    u = np.zeros(n + 1)
    v = np.zeros(m + 1)
    owner = np.zeros(m + 1, np.int64)  # row (1-based) assigned to column j (1-based); 0 = free
    way = np.zeros(m + 1, np.int64)
    minv = np.empty(m + 1)
    used = np.empty(m + 1, np.bool_)
    for i in range(1, n + 1):
        owner[0] = i
        j0 = 0
        minv[:] = np.inf
        used[:] = False
        while True:
            used[j0] = True
            i0 = owner[j0]
            delta = np.inf
            j1 = 0
            for j in range(1, m + 1):
                if not used[j]:
                    cur = c[i0 - 1, j - 1] - u[i0] - v[j]
                    if cur < minv[j]:
                        minv[j] = cur
                        way[j] = j0
                    if minv[j] < delta:
                        delta = minv[j]
                        j1 = j
            for j in range(m + 1):
                if used[j]:
                    u[owner[j]] += delta
                    v[j] -= delta
                else:
                    minv[j] -= delta
            j0 = j1
            if owner[j0] == 0:
                break
        while True:
            j1 = way[j0]
            owner[j0] = owner[j1]
            j0 = j1
            if j0 == 0:
                break
    out = np.full(t_n, -1, np.int64)
    for j in range(1, m + 1):
        if owner[j] != 0:
            if flip:
                out[j - 1] = owner[j] - 1
            else:
                out[owner[j] - 1] = j - 1
    return out


@numba.njit(cache=True)
def _hungarian(pred, cand, gate):  # type: ignore[no-untyped-def]
    """Index of the candidate assigned to each prediction (-1: none within its gate ``(T,)``)."""
    out = np.full(pred.shape[0], -1, np.int64)
    if pred.shape[0] == 0 or cand.shape[0] == 0:
        return out
    cost, big = _gated_cost(pred, cand, gate)
    col = _min_cost_assignment(cost)
    for t in range(pred.shape[0]):
        if col[t] >= 0 and not big[t, col[t]]:
            out[t] = col[t]
    return out


@numba.njit(cache=True)
def _near_and_shift(pred, vis, cand, search_px, reach_px, radius):  # type: ignore[no-untyped-def]
    """Candidates within ``reach_px`` of some visible prediction, and the frame's common shift (NaN if none).

    The shift is found by consensus: every displacement from a visible prediction to a candidate within
    ``search_px`` is a hypothesis, scored by how many visible predictions it brings within ``radius`` of a
    candidate (ties: the smaller sum of squared distances); the median displacement of those inliers is
    the shift. A large jump of the whole frame therefore cannot pair BBs with their neighbours."""
    m_n = cand.shape[0]
    t_n = pred.shape[0]
    best = np.full(m_n, np.inf)
    for t in range(t_n):
        if not vis[t]:
            continue
        for j in range(m_n):
            d = np.sqrt((cand[j, 0] - pred[t, 0]) ** 2 + (cand[j, 1] - pred[t, 1]) ** 2)
            if d < best[j]:
                best[j] = d
    kept = np.flatnonzero(best < reach_px)
    shift = np.full(2, np.nan)
    best_n, best_ss = 0, np.inf
    r2 = radius * radius
    for t in range(t_n):
        if not vis[t]:
            continue
        for m in kept:
            hx = cand[m, 0] - pred[t, 0]
            hy = cand[m, 1] - pred[t, 1]
            if hx * hx + hy * hy >= search_px * search_px:
                continue
            n_in, ss = 0, 0.0
            for u in range(t_n):
                if not vis[u]:
                    continue
                dmin = r2
                for q in kept:
                    d2 = (cand[q, 0] - pred[u, 0] - hx) ** 2 + (cand[q, 1] - pred[u, 1] - hy) ** 2
                    if d2 < dmin:
                        dmin = d2
                if dmin < r2:
                    n_in += 1
                ss += dmin
            if n_in > best_n or (n_in == best_n and ss < best_ss):
                best_n, best_ss = n_in, ss
                shift[0], shift[1] = hx, hy
    if best_n == 0:
        return kept, shift
    sx = np.empty(t_n)
    sy = np.empty(t_n)
    n_s = 0
    for u in range(t_n):  # refine: median displacement of the inliers
        if not vis[u]:
            continue
        dmin, jmin = r2, -1
        for q in kept:
            d2 = (cand[q, 0] - pred[u, 0] - shift[0]) ** 2 + (cand[q, 1] - pred[u, 1] - shift[1]) ** 2
            if d2 < dmin:
                dmin, jmin = d2, int(q)
        if jmin >= 0:
            sx[n_s] = cand[jmin, 0] - pred[u, 0]
            sy[n_s] = cand[jmin, 1] - pred[u, 1]
            n_s += 1
    shift[0] = _median(sx[:n_s])
    shift[1] = _median(sy[:n_s])
    return kept, shift


@numba.njit(cache=True)
def _realign(pred, vis, cand, idx):  # type: ignore[no-untyped-def]
    """Predictions moved by the affine map (6 or more matches, if it brings the matches closer) or the median
    shift (fewer) that takes matched predictions to their candidates."""
    rows = np.flatnonzero(idx >= 0)
    n_m = rows.size
    out = pred.copy()
    if n_m >= 6:
        # least squares by the normal equations, about the matches' mean (well conditioned: 3 unknowns)
        mx = 0.0
        my = 0.0
        for q in range(n_m):
            mx += pred[rows[q], 0] / n_m
            my += pred[rows[q], 1] / n_m
        ata = np.zeros((3, 3))
        atx = np.zeros(3)
        aty = np.zeros(3)
        a = np.empty(3)
        for q in range(n_m):
            a[0], a[1], a[2] = pred[rows[q], 0] - mx, pred[rows[q], 1] - my, 1.0
            for i in range(3):
                for j in range(3):
                    ata[i, j] += a[i] * a[j]
                atx[i] += a[i] * cand[idx[rows[q]], 0]
                aty[i] += a[i] * cand[idx[rows[q]], 1]
        cx = solve3(ata, atx)
        cy = solve3(ata, aty)
        before = np.empty(n_m)
        after = np.empty(n_m)
        for q in range(n_m):
            px, py = pred[rows[q], 0], pred[rows[q], 1]
            bx, by = cand[idx[rows[q]], 0], cand[idx[rows[q]], 1]
            fx = cx[0] * (px - mx) + cx[1] * (py - my) + cx[2]
            fy = cy[0] * (px - mx) + cy[1] * (py - my) + cy[2]
            before[q] = np.sqrt((px - bx) ** 2 + (py - by) ** 2)
            after[q] = np.sqrt((fx - bx) ** 2 + (fy - by) ** 2)
        if _median(after) < _median(before):
            for t in range(pred.shape[0]):
                if vis[t]:
                    dx, dy = pred[t, 0] - mx, pred[t, 1] - my
                    out[t, 0] = cx[0] * dx + cx[1] * dy + cx[2]
                    out[t, 1] = cy[0] * dx + cy[1] * dy + cy[2]
    elif n_m > 0:
        dx = np.empty(n_m)
        dy = np.empty(n_m)
        for q in range(n_m):
            dx[q] = cand[idx[rows[q]], 0] - pred[rows[q], 0]
            dy[q] = cand[idx[rows[q]], 1] - pred[rows[q], 1]
        mx, my = _median(dx), _median(dy)
        for t in range(pred.shape[0]):
            if vis[t]:
                out[t, 0] += mx
                out[t, 1] += my
    return out


@numba.njit(cache=True)
def _match(pred, cand, search_px, gate, radius):  # type: ignore[no-untyped-def]
    """:func:`match_frame` for predictions ``(T,2)``, candidates ``(M,2)`` and gates ``(T,)``."""
    t_n = pred.shape[0]
    pred = pred.copy()
    none = np.full(t_n, -1, np.int64)
    vis = np.empty(t_n, np.bool_)
    for t in range(t_n):
        vis[t] = np.isfinite(pred[t, 0]) and np.isfinite(pred[t, 1])
    if not vis.any() or cand.shape[0] == 0:
        return none, pred
    kept, shift = _near_and_shift(pred, vis, cand, search_px, search_px + 2.0 * gate.max(), radius)
    if kept.size == 0:
        return none, pred
    # loops, not fancy indexing and array expressions: those take seconds to compile on a first run
    near = np.empty((kept.size, 2))
    for q in range(kept.size):
        near[q, 0] = cand[kept[q], 0]
        near[q, 1] = cand[kept[q], 1]
    if np.isfinite(shift[0]):
        for t in range(t_n):
            if vis[t]:
                pred[t, 0] += shift[0]
                pred[t, 1] += shift[1]
    wide = np.empty(t_n)
    narrow = np.empty(t_n)
    for t in range(t_n):
        wide[t] = max(gate[t] * 1.5, radius)
        narrow[t] = max(gate[t], 0.5 * radius)
    idx = _hungarian(pred, near, wide)
    pred = _realign(pred, vis, near, idx)
    # parallax of BBs at different depths under a rotation is not affine; it grows with the allowed jump
    idx = _hungarian(pred, near, narrow)
    for t in range(t_n):
        if idx[t] >= 0:
            idx[t] = kept[idx[t]]
    return idx, pred


def match_frame(
    pred: NDArray[np.float64],
    cand: NDArray[np.float64],
    search_px: float,
    gate_px: NDArray[np.float64] | float,
    residual_px: float | None = None,
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Assign candidates ``(M,2)`` to predictions ``(T,2)`` (NaN = not expected) after removing the frame's
    common shift (the displacement most predictions agree on within ``residual_px``, default 1.5 gates) and,
    with 6 or more matches, an affine distortion. Returns the assignment (-1 = none) and the aligned
    predictions."""
    pred = np.ascontiguousarray(pred, dtype=np.float64)
    # a writable copy: a read-only array is another type to numba, compiled again (1.2 s on first use)
    gate = np.array(np.broadcast_to(np.asarray(gate_px, dtype=np.float64), (len(pred),)))
    radius = 1.5 * float(gate.max(initial=0.0)) if residual_px is None else float(residual_px)
    return _match(pred, np.ascontiguousarray(cand, dtype=np.float64), float(search_px), gate, radius)


@numba.njit(cache=True)
def _predict_from_rays(ray_o, ray_d, count, active, P, last_uv, P_last):  # type: ignore[no-untyped-def]
    """Pixels ``(T, 2)`` in the view of ``P (3,4)`` of active tracks: each track's last detection ``last_uv``
    moved by the nominal motion, from its last view (``P_last (T,3,4)``) to this one, of the least-squares
    intersection of its last rays (ring buffers ``(cap, W, 3)``; one ray: its point nearest the isocenter).
    The motion depends little on where along the rays the point lies, so the prediction inherits the
    error of the last detection's view, not that of a point triangulated through views that each err."""
    window = ray_o.shape[1]
    out = np.empty((active.shape[0], 2))
    A = np.empty((3, 3))
    b = np.empty(3)
    x = np.empty(3)
    for a in range(active.shape[0]):
        t = active[a]
        n = min(count[t], window)
        if n < 2:
            slot = (count[t] - 1) % window
            s = 0.0
            for i in range(3):
                s += ray_o[t, slot, i] * ray_d[t, slot, i]
            for i in range(3):
                x[i] = ray_o[t, slot, i] - s * ray_d[t, slot, i]
        else:
            A[:] = 0.0
            b[:] = 0.0
            for w in range(n):
                for i in range(3):
                    for j in range(3):
                        p = (1.0 if i == j else 0.0) - ray_d[t, w, i] * ray_d[t, w, j]
                        A[i, j] += p
                        b[i] += p * ray_o[t, w, j]
            x[:] = solve3(A, b)
        h0 = P[0, 0] * x[0] + P[0, 1] * x[1] + P[0, 2] * x[2] + P[0, 3]
        h1 = P[1, 0] * x[0] + P[1, 1] * x[1] + P[1, 2] * x[2] + P[1, 3]
        h2 = P[2, 0] * x[0] + P[2, 1] * x[1] + P[2, 2] * x[2] + P[2, 3]
        Q = P_last[a]
        g0 = Q[0, 0] * x[0] + Q[0, 1] * x[1] + Q[0, 2] * x[2] + Q[0, 3]
        g1 = Q[1, 0] * x[0] + Q[1, 1] * x[1] + Q[1, 2] * x[2] + Q[1, 3]
        g2 = Q[2, 0] * x[0] + Q[2, 1] * x[1] + Q[2, 2] * x[2] + Q[2, 3]
        out[a, 0] = last_uv[t, 0] + h0 / h2 - g0 / g2
        out[a, 1] = last_uv[t, 1] + h1 / h2 - g1 / g2
    return out


def _crowded(pred: NDArray[np.float64], within_px: float) -> NDArray[np.bool_]:
    """Predictions ``(T,2)`` closer than ``within_px`` to another one."""
    if len(pred) < 2:
        return np.zeros(len(pred), bool)
    d = np.linalg.norm(pred[:, None] - pred[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    with np.errstate(invalid="ignore"):
        return (d < within_px).any(1)


class _TrackStore:
    """Growing arrays of 2-D tracks: every detection, and the rays of each track's last ``window`` ones."""

    def __init__(self, window: int = 8, capacity: int = 256) -> None:
        self.window = window
        self.ray_o = np.zeros((capacity, window, 3))
        self.ray_d = np.zeros((capacity, window, 3))
        self.count = np.zeros(capacity, np.int64)
        self.last = np.zeros(capacity, np.int64)
        self.last_uv = np.zeros((capacity, 2))
        self.last_P = np.zeros((capacity, 3, 4))
        self.misses = np.zeros(capacity, np.int64)
        self.n = 0
        self.obs: list[tuple[int, NDArray[np.intp], NDArray[np.float64]]] = []  # (frame, track ids, uv)

    def _grow(self, need: int) -> None:
        cap = len(self.count)
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name in ("ray_o", "ray_d", "count", "last", "last_uv", "last_P", "misses"):
            old = getattr(self, name)
            arr = np.zeros((new,) + old.shape[1:], old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)

    def new_tracks(self, m: int) -> NDArray[np.intp]:
        """Ids of ``m`` new, empty tracks."""
        self._grow(self.n + m)
        ids = np.arange(self.n, self.n + m)
        self.n += m
        return ids

    def add(self, frame: int, ids: NDArray[np.intp], uv: NDArray[np.float64], view: ViewGeometry) -> None:
        """Detections ``uv (m,2)`` for tracks ``ids`` in ``frame``, seen through the one-view geometry ``view``."""
        if not len(ids):
            return
        origin, direction = view_rays(view, uv)
        slot = self.count[ids] % self.window
        self.ray_o[ids, slot] = origin
        self.ray_d[ids, slot] = direction
        self.count[ids] += 1
        self.last[ids] = frame
        self.last_uv[ids] = uv
        self.last_P[ids] = view.matrices[0]
        self.misses[ids] = 0
        self.obs.append((frame, ids, uv))


def view_rays(view: ViewGeometry, uv: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Source and unit directions ``(m, 3)`` of the rays through pixels ``uv (m, 2)`` of the one view ``view``."""
    c0, r0 = view.panel.center
    pts = view.D[0] + (uv[:, 0:1] - c0) * view.u[0] + (uv[:, 1:2] - r0) * view.v[0]
    d = pts - view.S[0]
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return view.S[0], d


@dataclass(frozen=True)
class FrameLinks:
    """What linking did with one frame: tracks continued and tracks started (ids and detections)."""

    continued: NDArray[np.intp]
    uv: NDArray[np.float64]
    started: NDArray[np.intp]
    started_uv: NDArray[np.float64]


class FrameLinker:
    """Links ball-like candidates into 2-D tracks one frame at a time (offline for a whole scan, or live).

    Each active track's next position is its last detection moved by the nominal motion of the point its last
    rays triangulate to (one detection: the point of its ray nearest the isocenter)."""

    def __init__(self, settings: TrackingSettings) -> None:
        self.settings = settings
        self.store = _TrackStore()
        self.active = np.zeros(0, np.int64)

    def step(self, p: int, c: NDArray[np.float64], view: ViewGeometry) -> FrameLinks:
        """Link the candidates ``c`` of frame ``p`` (nominal one-view geometry ``view``)."""
        s, store, active = self.settings, self.store, self.active
        ball = ball_like(c, s) if len(c) else np.zeros(0, bool)
        c = c[ball]
        uv_c = np.ascontiguousarray(c[:, :2])
        matched_c = np.zeros(len(c), bool)
        matched_t = np.zeros(len(active), bool)
        idx = np.full(len(active), -1)
        if len(active) and len(c):
            pred_a = _predict_from_rays(
                store.ray_o, store.ray_d, store.count, active, view.matrices[0], store.last_uv, store.last_P[active]
            )
            gates = s.gate_px * (1.0 + 0.5 * np.clip(p - store.last[active] - 1, 0, None)).astype(np.float64)
            idx, aligned = match_frame(pred_a, uv_c, s.search_px, gates, s.residual_px)
            matched_t = idx >= 0
            crowded = _crowded(aligned, s.ambiguous_px)
            store.misses[active[crowded]] = s.max_gap  # ended here: not continued, not coasting
            matched_t &= ~crowded
            matched_c[idx[matched_t]] = True
            store.add(p, active[matched_t], uv_c[idx[matched_t]], view)
        store.misses[active[~matched_t]] += 1
        still = active[matched_t | (store.misses[active] <= s.max_gap)]
        fresh = np.flatnonzero(~matched_c)
        ids = store.new_tracks(len(fresh))
        store.add(p, ids, uv_c[fresh], view)
        self.active = np.concatenate([still, ids])
        return FrameLinks(active[matched_t], uv_c[idx[matched_t]], ids, uv_c[fresh])

    def fragments(self, n_frames: int, min_length: int) -> NDArray[np.float64]:
        """2-D tracks ``(P, F, 2)`` of at least ``min_length`` detections (NaN where a track has none)."""
        store = self.store
        count = store.count[: store.n]
        keep = np.flatnonzero(count >= min_length)
        column = np.full(store.n, -1)
        column[keep] = np.arange(len(keep))
        out = np.full((n_frames, len(keep), 2), np.nan)
        for p, ids, uv in store.obs:
            col = column[ids]
            ok = col >= 0
            out[p, col[ok]] = uv[ok]
        return out


def link_fragments(cands: list[NDArray[np.float64]], s: TrackingSettings, nominal: ViewGeometry) -> NDArray[np.float64]:
    """2-D tracks ``(P, F, 2)`` over projections (NaN where a fragment has no detection), linked frame by frame
    (:class:`FrameLinker`) through the nominal geometry."""
    linker = FrameLinker(s)
    for p, c in enumerate(cands):
        linker.step(p, c, nominal[p : p + 1])
    return linker.fragments(len(cands), s.min_fragment)


def assign_to_predictions(
    cands: list[NDArray[np.float64]], predicted: NDArray[np.float64], s: TrackingSettings, gate_px: float
) -> NDArray[np.float64]:
    """Per frame, candidates assigned globally to predicted BB positions ``(P, K, 2)``; NaN where none fits,
    where two BBs overlap, or where the blob is distorted or much fainter than the BB usually is."""
    n, k = predicted.shape[:2]
    vis_all = all_finite(predicted)
    pred_all = np.where(vis_all[..., None], predicted, np.nan)
    records = np.full((n, k, len(CANDIDATE_FIELDS)), np.nan)
    gate = np.full(k, float(gate_px))
    for p in range(n):
        c = cands[p]
        if not len(c) or not vis_all[p].any():
            continue
        # predictions through a 3-D geometry: what the frame's shift leaves grows with the allowed jitter only
        idx, _ = _match(
            np.ascontiguousarray(pred_all[p]),
            np.ascontiguousarray(c[:, :2]),
            float(s.search_px),
            gate,
            max(1.5 * float(gate_px), 0.25 * (s.jitter_px + s.gate_px)),
        )
        rows = np.flatnonzero(idx >= 0)
        records[p, rows] = c[idx[rows]]
    uv = records[..., :2].copy()
    amp = records[..., AMP]
    shaped = ball_like(records.reshape(n * k, -1), s).reshape(n, k)  # NaN records (no match) are not shaped
    # overlap: two visible predictions closer than the BB size
    with np.errstate(invalid="ignore"):
        dd = np.linalg.norm(pred_all[:, :, None] - pred_all[:, None], axis=-1)
    dd[~np.isfinite(dd)] = np.inf
    dd[:, np.arange(k), np.arange(k)] = np.inf
    # two BBs whose projections touch: both are kept only when the detector resolved them into two blobs at
    # least a BB diameter apart (one blob of two, or a centroid pulled towards the other, is neither's)
    near = np.argmin(np.where(np.isfinite(dd), dd, np.inf), axis=2) if k else np.zeros((n, 0), int)
    other = np.take_along_axis(uv, near[..., None].repeat(2, -1), axis=1)
    with np.errstate(invalid="ignore"):
        resolved = np.linalg.norm(uv - other, axis=-1) >= s.diameter_px
    uv[(dd.min(2, initial=np.inf) < s.overlap_factor * s.diameter_px) & ~resolved] = np.nan
    shaped_amp = np.where(shaped, amp, np.nan)
    any_shaped = shaped.any(0)  # a BB never seen with a good shape has no typical amplitude (and no detection)
    typical = np.full(k, np.nan)
    typical[any_shaped] = np.nanmedian(shaped_amp[:, any_shaped], axis=0)
    with np.errstate(invalid="ignore"):
        faint = amp < s.min_amplitude_ratio * typical[None]
    uv[~shaped | faint] = np.nan
    return uv
