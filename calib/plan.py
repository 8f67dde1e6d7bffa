"""Planning where the BBs go: what a placement lets each view of an orbit calibrate, predicted without rendering.

For BB centres in the object frame and the orbit's nominal views: which BBs each view can use (wholly on the
panel, not overlapping another BB's projection, not behind metal of the object), how many, and the error the
calibration of each view is expected to have — the linearised bundle adjustment's covariance (every view's pose
and every BB's centre free, the similarity gauge held), at a given centroid noise, propagated to the projection
of points filling the field of view (pixels), the same figure a calibration reports as ``predicted_px``. A view
with fewer than four usable BBs cannot be calibrated from its own (NaN).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib.background import ObjectBackground
from calib.detect import relative_spread
from calib.model import ViewModel
from calib.quality import MIN_OWN_BBS, huber_threshold_px, placement_predicted_px
from calib.surfaces import TapeSurface, polar_angle
from orbitct.geometry import ViewGeometry
from orbitct.progress import ProgressCallback, report

#: a projected BB closer than this many diameters to another one is not counted (one blob of two)
OVERLAP_DIAMETERS = 1.25
#: a BB whose ray crosses more than this much metal of the object (mm) is not counted
METAL_CHORD_MM = 0.5
#: a BB whose detection window (its diameter and 2 px either side) holds the object's silhouette edge is measured
#: this many times noisier across the edge than the centroid noise a calibration reports (an RMS over all its
#: detections, these included): the background there is no plane. Experiment A at 512 px: 0.2-0.47 px across the
#: edge, 0.06-0.1 px elsewhere, 0.11 px reported; with 2, its own placement's predicted error is 0.92-1.04 times the
#: measured one at 256 and 512 px (3: 1.1-1.3; without edges: 0.8)
EDGE_NOISE_FACTOR = 2.0
#: the planner's best random placements (ranked by geometry alone) ranked again with the object's background
_RERANKED = 10
#: the lighter search each count gets when the fewest BBs for a target error are looked for
_COUNT_SEARCH = {"trials": 80, "rounds": 2}
#: the search's moves near a BB's place: normal steps of (degrees of angle, mm of height), shrinking each round
_LOCAL_STEP = (20.0, 15.0)
_LOCAL_SHRINK = 0.6
#: a round of moves that lowers the score by less than this share ends the search
_ROUND_GAIN = 0.005
#: polar angles at which the silhouette is looked for (degrees apart)
_OUTLINE_STEP_DEG = 6.0


@dataclass(frozen=True)
class PlanPrediction:
    """What a placement lets each view calibrate."""

    usable: NDArray[np.bool_]  # (P, K): BB k can be used in view p
    n_bbs: NDArray[np.intp]  # (P,)
    predicted_px: NDArray[np.float64]  # (P,): NaN where fewer than four BBs are usable
    noise_px: float

    @property
    def under_determined(self) -> NDArray[np.intp]:
        """Views with fewer than four usable BBs."""
        return np.flatnonzero(self.n_bbs < MIN_OWN_BBS)

    def summary(self) -> dict[str, Any]:
        """Counts and error figures (px) over the views."""
        ok = np.isfinite(self.predicted_px)
        p = self.predicted_px[ok]
        return {
            "views": int(self.n_bbs.size),
            "under_determined": int(self.under_determined.size),
            "bbs_min": int(self.n_bbs.min()) if self.n_bbs.size else 0,
            "bbs_median": float(np.median(self.n_bbs)) if self.n_bbs.size else 0.0,
            "predicted_px_median": float(np.median(p)) if p.size else float("nan"),
            "predicted_px_max": float(p.max()) if p.size else float("nan"),
            "predicted_px_rms": float(np.sqrt(np.mean(p**2))) if p.size else float("nan"),
        }


def usable_bbs(
    geometry: ViewGeometry, xyz: NDArray[np.float64], diameter_mm: float, metal: list[Any] | None = None
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Per view, the BBs ``xyz`` (K, 3) that are wholly on the panel, clear of every other BB's projection and,
    with ``metal`` (primitives with ``chords``, such as a phantom's screws), not behind metal; and their pixels."""
    uv = geometry.project(xyz)  # (P, K, 2)
    det = geometry.panel
    d_px = geometry.projected_size_px(diameter_mm)
    margin = 0.5 * d_px[:, None] + 1.0
    ok = (
        np.isfinite(uv).all(-1)
        & (uv[..., 0] >= margin)
        & (uv[..., 0] <= det.cols - 1 - margin)
        & (uv[..., 1] >= margin)
        & (uv[..., 1] <= det.rows - 1 - margin)
    )
    dd = np.linalg.norm(uv[:, :, None] - uv[:, None], axis=-1)
    k = xyz.shape[0]
    dd[:, np.arange(k), np.arange(k)] = np.inf
    ok &= ~(dd < OVERLAP_DIAMETERS * d_px[:, None, None]).any(-1)
    if metal:
        origin = np.repeat(geometry.S, k, axis=0)
        direction = (xyz[None] - geometry.S[:, None]).reshape(-1, 3)
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        chord = np.add.reduce([np.asarray(m.chords(origin, direction)) for m in metal]).reshape(ok.shape)
        ok &= chord <= METAL_CHORD_MM
    return ok, uv


def edge_noise(
    geometry: ViewGeometry, xyz: NDArray[np.float64], diameter_mm: float, surface: TapeSurface
) -> NDArray[np.float64]:
    """Per view and BB, the detection's noise covariance relative to the centroid noise ``(P, K, 2, 2)``: the
    identity, or :data:`EDGE_NOISE_FACTOR` squared across the silhouette edge of ``surface`` (its outline at the
    BB's height, projected) where that edge lies within the BB's detection window."""
    k = xyz.shape[0]
    angles = np.radians(np.arange(0.0, 360.0, _OUTLINE_STEP_DEG))
    a = np.tile(angles, k)
    z = np.repeat(xyz[:, 2], angles.size)
    outline = surface.points(a, z, 0.0)
    covered = surface.covers(a, z)
    outline[~covered] = np.nan
    uv = geometry.project(xyz)  # (P, K, 2)
    up = geometry.project(xyz + [0.0, 0.0, 1.0]) - uv  # the object's axis in the image: the edge runs along it
    across = np.stack([up[..., 1], -up[..., 0]], -1)
    across /= np.linalg.norm(across, axis=-1, keepdims=True)
    rel = geometry.project(outline).reshape(geometry.n_views, k, angles.size, 2) - uv[:, :, None]
    s = rel[..., 0] * across[..., 0, None] + rel[..., 1] * across[..., 1, None]  # (P, K, T) px across the edge
    if not covered.all():  # heights or angles without surface: no edge there (none at all: never exposed)
        lo, hi = np.where(np.isnan(s), np.inf, s).min(-1), np.where(np.isnan(s), -np.inf, s).max(-1)
    else:
        lo, hi = s.min(-1), s.max(-1)
    gap = np.where(np.abs(lo) < np.abs(hi), -lo, hi)  # px from the centre to the nearer edge, > 0 inside the outline
    d_px = geometry.projected_size_px(diameter_mm)
    # the detector's window reaches ceil(d) + 2 px from the centre, and the background's bend inside the edge 2 px
    # further; a BB more than 2 px outside the outline sees only its own side (experiment A at 512 px)
    exposed = (gap >= -2.0) & (gap <= (np.ceil(d_px) + 4.0)[:, None])
    var = np.broadcast_to(np.eye(2), exposed.shape + (2, 2)).copy()
    var[exposed] += (EDGE_NOISE_FACTOR**2 - 1.0) * np.einsum("ma,mb->mab", across[exposed], across[exposed])
    return var


def predict_placement(
    geometry: ViewGeometry,
    xyz: NDArray[np.float64],
    diameter_mm: float,
    *,
    noise_px: float = 0.1,
    metal: list[Any] | None = None,
    surface: TapeSurface | None = None,
    background: ObjectBackground | None = None,
    moved: Sequence[ViewGeometry] = (),
) -> PlanPrediction:
    """The usable BBs of every view of ``geometry`` (nominal) and each view's predicted calibration error (px) at
    centroid noise ``noise_px`` (the calibrations of simulated scans measure 0.05-0.15 px); with the object's
    ``background`` (a model of what lies behind each BB), each detection's noise follows the photons and the
    structure under it (:class:`calib.background.ObjectBackground`); else with the object's ``surface``, BBs at its
    silhouette edge are counted noisier across it (:func:`edge_noise`). ``moved``: the same views with the orbit's
    expected motion errors (samples of an error profile); a BB counts in a view only where it is usable in each."""
    usable, uv = usable_bbs(geometry, xyz, diameter_mm, metal)
    for views in moved:
        usable &= usable_bbs(views, xyz, diameter_mm, metal)[0]
    n = usable.sum(1)
    predicted = np.full(geometry.n_views, np.nan)
    own = n >= MIN_OWN_BBS
    if own.sum() >= 2:
        idx = np.flatnonzero(own)
        seen = np.where(usable[idx, :, None], uv[idx], np.nan)
        placed = np.isfinite(seen).all(-1).sum(0) >= 3  # a BB seen in fewer views has no position of its own
        visible = seen[:, placed]
        in_view = np.isfinite(visible).all(-1)
        if background is not None:  # noise_px, as a calibration reports it, holds typical shifts: the rest is random
            random_px = background.random_noise_px(noise_px)
            var: NDArray[np.float64] | None = background.variance(geometry, xyz[placed], diameter_mm, random_px)[idx]
            bias = background.bias(geometry, xyz[placed], diameter_mm)[idx]
            rms = background.background_rms(geometry, xyz[placed], diameter_mm, random_px)[idx]
            predicted[idx] = placement_predicted_px(
                ViewModel(geometry[idx]),
                xyz[placed],
                visible,
                random_px,
                var,
                huber_threshold_px(noise_px),
                bias,
                relative_spread(np.where(in_view, rms, np.nan)),
            )
        else:
            var = None if surface is None else edge_noise(geometry[idx], xyz[placed], diameter_mm, surface)
            spread = (
                None
                if var is None
                else relative_spread(np.where(in_view, np.sqrt(0.5 * np.trace(var, axis1=-2, axis2=-1)), np.nan))
            )
            predicted[idx] = placement_predicted_px(
                ViewModel(geometry[idx]), xyz[placed], visible, noise_px, var, spread=spread
            )
    return PlanPrediction(usable, n, predicted, float(noise_px))


def metal_of(phantom: Any) -> list[Any]:
    """The metal primitives of a phantom other than its BBs (screws, wires)."""
    return [p for p in phantom.primitives if p.is_metal and not str(p.label).startswith("bb")]


@dataclass(frozen=True)
class KeepOut:
    """A patch of the surface where no BB may go (a wound, a label, where the object is held): polar angles from
    ``angle_from_deg`` counterclockwise to ``angle_to_deg`` (through 0 when ``to < from``; 0 to 360: the whole
    turn) between two heights."""

    angle_from_deg: float
    angle_to_deg: float
    z_min_mm: float
    z_max_mm: float

    @classmethod
    def parse(cls, text: str) -> KeepOut:
        """``FROM:TO,ZMIN:ZMAX`` (degrees, mm), e.g. ``300:60,-20:10``; ValueError naming what is wrong."""
        try:
            (a0, a1), (z0, z1) = ([float(v) for v in part.split(":")] for part in text.split(","))
        except ValueError:
            raise ValueError(
                f"keep-out {text!r}: expected FROM_DEG:TO_DEG,ZMIN_MM:ZMAX_MM (e.g. 300:60,-20:10)"
            ) from None
        if not z0 < z1:
            raise ValueError(f"keep-out {text!r}: the lower height {z0:g} must be below the upper {z1:g}")
        if a1 - a0 >= 360.0:
            return cls(0.0, 360.0, z0, z1)
        if a0 % 360.0 == a1 % 360.0:
            raise ValueError(f"keep-out {text!r}: from {a0:g} to {a1:g} degrees is no patch (the whole turn is 0:360)")
        return cls(a0 % 360.0, a1 % 360.0, z0, z1)

    @property
    def span_deg(self) -> float:
        """How far the patch reaches round the object (degrees, up to 360)."""
        return (
            360.0
            if self.angle_to_deg - self.angle_from_deg >= 360.0
            else (self.angle_to_deg - self.angle_from_deg) % 360.0
        )

    def contains(self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether surface points (polar angle, height) lie in the patch."""
        a = np.degrees(angle_rad) % 360.0
        inside = (a - self.angle_from_deg) % 360.0 <= self.span_deg
        return inside & (z_mm >= self.z_min_mm) & (z_mm <= self.z_max_mm)


@dataclass(frozen=True)
class Placement:
    """Planned BBs: their addresses on the surface (angle, rad, as the surface reads it — the polar angle is
    :func:`calib.surfaces.polar_angle` — and height, mm), their centres, and the prediction."""

    angle_rad: NDArray[np.float64]
    z_mm: NDArray[np.float64]
    xyz: NDArray[np.float64]
    prediction: PlanPrediction
    score: float


def placement_score(pred: PlanPrediction) -> float:
    """What the search minimises: the power mean of order 4 of the predicted errors over the views (the worst views
    weigh most, as a view that cannot be calibrated breaks the reconstruction, yet every view counts: a smoother
    landscape than the worst view's alone, which one move of a BB seldom changes), plus a view's worth of a large
    error for every view left under-determined."""
    p = pred.predicted_px[np.isfinite(pred.predicted_px)]
    if p.size == 0:
        return float("inf")
    return float(np.mean(p**4) ** 0.25 + 10.0 * pred.under_determined.size / pred.n_bbs.size)


def check_room(surface: TapeSurface, keep_out: Sequence[KeepOut], rng: np.random.Generator | None = None) -> None:
    """ValueError when the ``keep_out`` patches leave no place on ``surface`` for a BB (4000 random places tried)."""
    rng = rng if rng is not None else np.random.default_rng(0)
    probe = (rng.uniform(0, 2 * np.pi, 4000), rng.uniform(surface.z_min_mm, surface.z_max_mm, 4000))
    if not (_allowed(surface, probe[0], probe[1], keep_out) & surface.covers(*probe)).any():
        raise ValueError("the keep-out zones cover the whole surface: no place is left for a BB")


def plan_placement(
    geometry: ViewGeometry,
    surface: TapeSurface,
    n_bbs: int,
    diameter_mm: float,
    *,
    noise_px: float = 0.1,
    metal: list[Any] | None = None,
    keep_out: Sequence[KeepOut] = (),
    seed: int = 0,
    trials: int = 200,
    rounds: int = 5,
    moves: int = 12,
    min_spacing_mm: float = 25.0,
    background: ObjectBackground | None = None,
    moved: Sequence[ViewGeometry] = (),
    progress: ProgressCallback | None = None,
) -> Placement:
    """Search BB positions on ``surface`` outside the ``keep_out`` patches that minimise :func:`placement_score` for
    the views of ``geometry``: ``trials`` random placements (BBs at least ``min_spacing_mm`` apart, placed one at a
    time), then up to ``rounds`` rounds of moving each BB to the best of ``moves`` places, half anywhere and half near
    its place (steps shrinking round by round), until a round gains less than 0.5 %. The search scores about 125 of
    the views; the result is predicted on all. With the object's ``background`` (see :func:`predict_placement`) the
    trials are ranked without it (it costs a ray fan per BB and view) and the best few ranked again with it.
    ``moved`` as for :func:`predict_placement`. ``progress`` hears stage ``plan``: trials, re-ranked placements and
    BB moves done of all."""
    rng = np.random.default_rng(seed)
    every = max(1, geometry.n_views // 125)
    coarse, coarse_moved = geometry[::every], [views[::every] for views in moved]
    check_room(surface, keep_out, rng)

    def spaced(ang: NDArray[np.float64], z: NDArray[np.float64]) -> bool:
        xyz = surface.points(ang, z, diameter_mm)
        d = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
        return bool((d[np.triu_indices(len(xyz), 1)] >= min_spacing_mm).all())

    def draw(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        ang, z = np.empty(0), np.empty(0)
        for _ in range(1000):  # uniform over the surface less the keep-out zones
            a, h = rng.uniform(0, 2 * np.pi, 4 * n), rng.uniform(surface.z_min_mm, surface.z_max_mm, 4 * n)
            keep = _allowed(surface, a, h, keep_out) & surface.covers(a, h)
            ang, z = np.concatenate([ang, a[keep]]), np.concatenate([z, h[keep]])
            if ang.size >= n:
                return ang[:n], z[:n]
        raise ValueError("the keep-out zones leave less than 0.1 % of the surface: no room to place BBs")

    def draw_spaced(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """``n`` places one at a time, each uniform over what the ones before leave free (None: no room left);
        drawing all at once and keeping only spaced sets almost never succeeds for many BBs (16 on experiment B)."""
        ang, z = np.empty(0), np.empty(0)
        while ang.size < n:
            a, h = draw(64)
            if ang.size:
                far = (
                    np.linalg.norm(
                        surface.points(a, h, diameter_mm)[:, None] - surface.points(ang, z, diameter_mm)[None], axis=-1
                    ).min(1)
                    >= min_spacing_mm
                )
                if not far.any():
                    return None
                a, h = a[far], h[far]
            ang, z = np.append(ang, a[0]), np.append(z, h[0])
        return ang, z

    def score(
        ang: NDArray[np.float64], z: NDArray[np.float64], object_background: ObjectBackground | None = background
    ) -> float:
        return placement_score(
            predict_placement(
                coarse,
                surface.points(ang, z, diameter_mm),
                diameter_mm,
                noise_px=noise_px,
                metal=metal,
                surface=surface,
                background=object_background,
                moved=coarse_moved,
            )
        )

    def near_or_anywhere(a0: float, z0: float, scale: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``moves`` places for one BB: half anywhere on the surface, half near where it is (``scale`` times
        :data:`_LOCAL_STEP`), as places anywhere are rarely better once the placement is good."""
        n_near = moves // 2
        a_far, z_far = draw(moves - n_near)
        a = a0 + rng.normal(0, scale * np.radians(_LOCAL_STEP[0]), 8 * n_near)
        h = z0 + rng.normal(0, scale * _LOCAL_STEP[1], 8 * n_near)
        keep = np.flatnonzero(_allowed(surface, a, h, keep_out) & surface.covers(a, h))[:n_near]
        return np.concatenate([a_far, a[keep]]), np.concatenate([z_far, h[keep]])

    steps = trials + (_RERANKED if background is not None else 0) + rounds * n_bbs
    ranked: list[tuple[float, NDArray[np.float64], NDArray[np.float64]]] = []
    for t in range(trials):
        drawn = draw_spaced(n_bbs)
        if drawn is not None:
            ranked.append((score(*drawn, None), *drawn))
        if t % 10 == 9:
            report(progress, "plan", t + 1, steps, f"{n_bbs} BBs: random placements")
    if not ranked:
        raise ValueError(
            f"{n_bbs} BBs {min_spacing_mm:g} mm apart do not fit on the surface; fewer BBs or less spacing"
        )
    ranked.sort(key=lambda t: t[0])
    if background is not None:
        report(progress, "plan", trials, steps, f"{n_bbs} BBs: the best {_RERANKED} ranked with the object")
        ranked = sorted(((score(a, h), a, h) for _, a, h in ranked[:_RERANKED]), key=lambda t: t[0])
    s_best, ang, z = ranked[0]
    for r in range(rounds):
        s_round = s_best
        for k in range(n_bbs):
            report(progress, "plan", steps - (rounds - r) * n_bbs + k, steps, f"{n_bbs} BBs: moving BB {k + 1}")
            for a_new, z_new in zip(*near_or_anywhere(ang[k], z[k], _LOCAL_SHRINK**r), strict=True):
                a2, z2 = ang.copy(), z.copy()
                a2[k], z2[k] = a_new, z_new
                if not spaced(a2, z2):
                    continue
                s2 = score(a2, z2)
                if s2 < s_best:
                    s_best, ang, z = s2, a2, z2
        if s_best > (1 - _ROUND_GAIN) * s_round:
            break  # the round no longer pays
    report(progress, "plan", steps, steps, f"{n_bbs} BBs: predicted on every view")
    xyz = surface.points(ang, z, diameter_mm)
    full = predict_placement(
        geometry, xyz, diameter_mm, noise_px=noise_px, metal=metal, surface=surface, background=background, moved=moved
    )
    return Placement(ang, z, xyz, full, placement_score(full))


def hand_spiral(
    surface: TapeSurface, n_bbs: int, diameter_mm: float, *, seed: int = 0, keep_out: Sequence[KeepOut] = ()
) -> NDArray[np.float64]:
    """BB centres as a person tapes them by hand in the published workflow: one turn round the object, an equal angle
    apart (from a random start), climbing evenly between a tenth of the height from either end, each off by up to
    10 degrees and 4 mm, or a quarter of the step (experiment A's own placement is such a spiral). ValueError where
    the surface has none, or a BB would fall in one of the ``keep_out`` patches."""
    rng = np.random.default_rng([seed, 1811])
    k = np.arange(n_bbs)
    step_deg, span = 360.0 / n_bbs, surface.z_max_mm - surface.z_min_mm
    step_mm = 0.8 * span / max(n_bbs - 1, 1)
    off_deg, off_mm = min(10.0, step_deg / 4), min(4.0, step_mm / 4)  # never as close as to swap places
    angle = np.radians(rng.uniform(0, 360) + step_deg * k + rng.uniform(-off_deg, off_deg, n_bbs))
    z = surface.z_min_mm + 0.1 * span + step_mm * k + rng.uniform(-off_mm, off_mm, n_bbs)
    if not surface.covers(angle, z).all():
        raise ValueError("a hand-made spiral leaves the surface (an outline with holes?)")
    if not _allowed(surface, angle, z, keep_out).all():
        raise ValueError("a hand-made spiral puts a BB in a keep-out zone")
    return surface.points(angle, z, diameter_mm)


def _allowed(
    surface: TapeSurface, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64], keep_out: Sequence[KeepOut]
) -> NDArray[np.bool_]:
    """Which addresses (angle, height) of ``surface`` lie outside every patch (patches are in polar angles)."""
    out = np.ones(np.shape(angle_rad), bool)
    if keep_out:
        polar = polar_angle(surface, angle_rad, z_mm)
        for zone in keep_out:
            out &= ~zone.contains(polar, z_mm)
    return out


@dataclass(frozen=True)
class CountSuggestion:
    """The fewest BBs whose planned placement reaches a target accuracy, and what each count tried reached."""

    target_px: float
    n_bbs: int | None  # None: not reached with the most BBs tried
    tried: dict[int, dict[str, Any]]  # count -> the planned placement's prediction summary


@dataclass(frozen=True)
class PlacementCost:
    """Seconds this machine takes to score a placement as :func:`plan_placement` does, per BB: without the object's
    background, with each BB's share of it already cached, and for that share (paid once per new BB position)."""

    plain_s: float
    cached_s: float
    new_bb_s: float
    reranked: int  # the best trials scored again with the background (none without one)

    def search_s(self, n_bbs: int, *, trials: int = 200, rounds: int = 5, moves: int = 12, **_: Any) -> float:
        """Seconds :func:`plan_placement` of ``n_bbs`` BBs takes with these search settings, every round of moves
        run (a round that gains little ends the search sooner): random trials scored without the background, the
        best few scored with it (all their BBs new), then each move (one BB new)."""
        again = self.reranked * n_bbs * (self.cached_s + self.new_bb_s)
        moving = rounds * n_bbs * moves * (n_bbs * self.cached_s + self.new_bb_s)
        return trials * n_bbs * self.plain_s + again + moving

    def count_s(self, n_min: int, n_max: int, **search: Any) -> float:
        """Seconds :func:`suggest_bb_count` takes at most (every count from ``n_min`` to ``n_max`` planned)."""
        return sum(self.search_s(n, **{**_COUNT_SEARCH, **search}) for n in range(n_min, n_max + 1))


def placement_cost(
    geometry: ViewGeometry,
    surface: TapeSurface,
    n_bbs: int,
    diameter_mm: float,
    *,
    noise_px: float = 0.1,
    metal: list[Any] | None = None,
    background: ObjectBackground | None = None,
    moved: Sequence[ViewGeometry] = (),
    **_: Any,
) -> PlacementCost:
    """:class:`PlacementCost` measured now: ``n_bbs`` BBs placed on ``surface`` scored on the views the search
    scores, without the ``background`` and twice with it (its BBs' share is computed once). About a second; best
    measured once the kernels are loaded (after a first prediction)."""
    every = max(1, geometry.n_views // 125)
    coarse, coarse_moved = geometry[::every], [views[::every] for views in moved]
    rng = np.random.default_rng(0)
    ang, z = rng.uniform(0, 2 * np.pi, 64 * n_bbs), rng.uniform(surface.z_min_mm, surface.z_max_mm, 64 * n_bbs)
    on = np.flatnonzero(surface.covers(ang, z))[:n_bbs]
    xyz = surface.points(ang[on], z[on], diameter_mm)
    placed = max(len(on), 1)

    def timed(object_background: ObjectBackground | None) -> float:
        t = time.perf_counter()
        predict_placement(
            coarse,
            xyz,
            diameter_mm,
            noise_px=noise_px,
            metal=metal,
            surface=surface,
            background=object_background,
            moved=coarse_moved,
        )
        return (time.perf_counter() - t) / placed

    plain = timed(None)
    if background is None:
        return PlacementCost(plain, plain, 0.0, 0)
    first, again = timed(background), timed(background)
    return PlacementCost(plain, again, max(first - again, 0.0), _RERANKED)


def suggest_bb_count(
    geometry: ViewGeometry,
    surface: TapeSurface,
    diameter_mm: float,
    target_px: float,
    *,
    n_min: int = MIN_OWN_BBS,
    n_max: int = 20,
    **plan_options: Any,
) -> CountSuggestion:
    """The fewest BBs (from ``n_min`` up to ``n_max``) whose planned placement leaves no view under-determined and
    predicts every view's error at or below ``target_px``; each count is planned with ``plan_options`` (a lighter
    search than a final plan's is enough to rank counts). ``progress`` hears stage ``count`` (counts tried) besides
    each count's ``plan``."""
    options = {**_COUNT_SEARCH, **plan_options}
    progress = options.get("progress")
    tried: dict[int, dict[str, Any]] = {}
    for n in range(n_min, n_max + 1):
        report(progress, "count", n - n_min, n_max - n_min + 1, f"planning {n} BBs")
        try:
            placed = plan_placement(geometry, surface, n, diameter_mm, **options)
        except ValueError:  # n BBs no longer fit at the spacing: more will not either
            break
        summary = placed.prediction.summary()
        tried[n] = summary
        report(
            progress,
            "count",
            n - n_min + 1,
            n_max - n_min + 1,
            f"{n} BBs: worst view {summary['predicted_px_max']:.3g} px",
            worst_px=float(summary["predicted_px_max"]),
        )
        if summary["under_determined"] == 0 and summary["predicted_px_max"] <= target_px:
            return CountSuggestion(target_px, n, tried)
    return CountSuggestion(target_px, None, tried)


__all__ = [
    "EDGE_NOISE_FACTOR",
    "METAL_CHORD_MM",
    "OVERLAP_DIAMETERS",
    "CountSuggestion",
    "KeepOut",
    "Placement",
    "PlacementCost",
    "PlanPrediction",
    "check_room",
    "edge_noise",
    "hand_spiral",
    "metal_of",
    "placement_cost",
    "placement_score",
    "plan_placement",
    "predict_placement",
    "suggest_bb_count",
    "usable_bbs",
]
