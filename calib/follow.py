"""Following the BBs frame by frame while a scan runs: the live warnings, their settings and the follower that
raises them (in :mod:`calib.live`'s worker process).

The :class:`Follower` takes each frame's BB candidates, links them to the last frames'
(:class:`calib.track.FrameLinker`), watches every BB seen often enough through a point of its own (the rays of its
detections) and the frame's pose, and warns when a BB is lost, leaves the panel, looks distorted, when too few
are seen, or when the object moved.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from calib.detect import N_FIELDS, FrameDetector
from calib.errors import CalibrationError
from calib.framepose import FramePose, StepWatch, fit_frame_pose
from calib.model import ViewModel, ViewState
from calib.options import checked_options
from calib.pipeline import frame_detector, motion_px, projected_diameter_px
from calib.search import SearchPlan
from calib.track import (
    FrameLinker,
    FrameLinks,
    TrackingSettings,
    ball_like,
    like_the_others,
    match_frame,
    view_rays,
)
from calib.window import SlidingBundle
from orbitct.geometry import ViewGeometry
from orbitct.livewarnings import WarningKind
from orbitct.scanfile import ImageKey


class LiveCalibrationError(CalibrationError):
    """Live calibration cannot run as asked (no BB size, frames out of order, used after it finished)."""


@dataclass(frozen=True)
class LiveWarning:
    """Something the operator should know while the scan runs: ``kind`` (see :data:`orbitct.livewarnings.WARNING_KINDS`), the scan
    frame it was raised at, the first frame it concerns, and a sentence naming frames and positions."""

    kind: WarningKind
    frame: int
    since_frame: int
    message: str
    uv: tuple[float, float] | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "kind": self.kind,
            "frame": self.frame,
            "since_frame": self.since_frame,
            "message": self.message,
            "uv": None if self.uv is None else list(self.uv),
        }


@dataclass
class LiveSettings:
    """When live calibration warns (frames are scan frames; positions are detector pixels)."""

    lost_frames: int = 10  # a followed BB missing for more than this many frames where it should be visible
    min_bbs: int = 4  # a view with fewer BBs cannot be calibrated from its own
    watch_after: int = 15  # a BB is watched (lost / left the field of view) once followed this many frames
    max_pending: int = 256  # frames waiting for detection beyond this are detected from the file after the scan
    edge_margin_px: float = 2.0  # extra margin inside the panel for "should be visible"


#: a watched BB missing this many frames in a row, with a blob where it should be that is not ball-like, is reported
#: distorted (a BB missing from one or two frames, as one crossing a bone edge is, costs the calibration nothing)
DISTORTED_FRAMES = 3

#: frames whose pose misses its BBs by more than this many centroid noises do not feed the watch for a moved object
WATCH_MISFIT = 3.0

#: a watched BB's 3-D point is fixed after this many rays: the frame the live poses and the motion watch refer to
#: stays that of the scan's start (a point that kept absorbing rays would follow an object that moved)
POINT_RAYS = 60

#: a watched BB's rays (through the nominal views) miss its point by at most this RMS (mm; or twice the options'
#: jitter_mm where that is more), and by at most WATCH_SCATTER_RATIO times the other watched BBs' median: every BB
#: shares the orbit's errors, so its rays scatter like the others' (BBs on the paper's bench profile 1.6-4.2 mm at
#: 15-60 rays, at most 1.3 times their median; at 192 px, BBs 2 px across, 0.4-1.2 mm, and tracks that followed
#: two BBs or a structure 2.3-10 mm). Beyond either the point is no BB's and it is no longer watched: its warnings
#: would be false ('lost' where no BB was)
WATCH_SCATTER_MM = 6.0
WATCH_SCATTER_RATIO = 3.0


def _record_at(candidates: NDArray[np.float64], uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """The candidate record (of one frame's ``candidates``) whose centroid is nearest to ``uv``."""
    return candidates[np.argmin(np.linalg.norm(candidates[:, :2] - uv, axis=1))]


@dataclass
class _Watched:
    """A BB followed long enough to be missed: its rays' normal equations (for its 3-D point) and state."""

    A: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 3)))
    b: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    c: float = 0.0  # the rays' sum of o^T P o: with A and b, their squared distances from any point
    count: int = 0
    last_frame: int = -1
    last_uv: tuple[float, float] = (0.0, 0.0)
    missing_since: int | None = None  # scan frame since when it is not found where it should be visible
    track: int = -1  # the 2-D track its latest detection belongs to
    warned: bool = False
    outside: bool = False
    look: NDArray[np.float64] = field(default_factory=lambda: np.full(N_FIELDS, np.nan))  # median blob record

    def add_ray(self, origin: NDArray[np.float64], direction: NDArray[np.float64]) -> None:
        self.count += 1
        if self.count > POINT_RAYS:
            return
        P = np.eye(3) - np.outer(direction, direction)
        self.A += P
        self.b += P @ origin
        self.c += float(origin @ P @ origin)

    def point(self) -> NDArray[np.float64]:
        return np.linalg.lstsq(self.A, self.b, rcond=None)[0].astype(np.float64)

    def scatter_mm(self) -> float:
        """RMS distance of its rays from its point (mm)."""
        x = self.point()
        n = min(self.count, POINT_RAYS)
        return float(np.sqrt(max(float(self.c - 2.0 * x @ self.b + x @ self.A @ x), 0.0) / max(n, 1)))


class Follower:
    """What runs in the worker process: detection of every projection, frame-to-frame linking, watched BBs and
    the warnings (sent through ``emit``)."""

    def __init__(
        self,
        nominal: ViewGeometry,
        image_key: NDArray[np.integer[Any]],
        diameter_mm: float,
        settings: LiveSettings,
        options: dict[str, Any],
        emit: Callable[[str, Any], None],
    ) -> None:
        self.nominal = nominal
        self.image_key = np.asarray(image_key)
        self.diameter_mm = float(diameter_mm)
        self.settings = settings
        self.opt = checked_options("bundle", {**options, "diameter_mm": diameter_mm})
        self.emit = emit
        proj = np.flatnonzero(self.image_key == ImageKey.PROJECTION)
        self._proj_index = proj
        self.n_projections = int(proj.size)
        self.d_px = projected_diameter_px(nominal[proj], self.diameter_mm) if proj.size else 1.0
        self.tracking = TrackingSettings(
            diameter_px=self.d_px,
            motion_px=motion_px(nominal[proj]) if proj.size else 0.0,
            jitter_px=self.opt.jitter_mm * self.d_px / self.diameter_mm,
        )
        self.linker = FrameLinker(self.tracking)
        # the candidates as an offline calibration finds them: the same search, frame by frame
        self.plan = SearchPlan.for_scan(self.d_px, self.tracking.motion_px, self.tracking.jitter_px, self.opt.bb_search)
        self.candidates: list[NDArray[np.float64] | None] = []
        self.floors: list[float] = []  # per projection, :attr:`calib.detect.FrameSearch.floor` (NaN: after the scan)
        self.bbs_per_frame: list[int] = []
        self.detect_s = 0.0
        self._dark_sum: NDArray[np.float64] | None = None
        self._flat_sum: NDArray[np.float64] | None = None
        self._n_dark = 0
        self._n_flat = 0
        self._single_flats: list[NDArray[Any]] = []
        self._detector: FrameDetector | None = None
        self._deferred: list[int] = []  # projection numbers detected from the file after the scan
        self._watched: dict[int, _Watched] = {}  # by the track that found it
        self._tracks_seen: set[int] = set()  # tracks already considered as new BBs
        self._few_since: int | None = None
        self._last_distorted = -(10**9)
        self._behind_warned = False
        self._next_index = 0
        self._last_pose: ViewState | None = None
        self._misfits: deque[float] = deque(maxlen=50)
        # the orbit's errors are smooth along the orbit: the jump watch's baseline is a fifth of the scan (40 to 80
        # frames), so that a short scan's faster drift per frame still fits its parabola
        self._steps = StepWatch(baseline=int(np.clip(0.2 * self.n_projections, 40, 80)))
        self.rpe_mm: list[float] = []  # per frame with a pose, in order
        self.window = SlidingBundle()
        self._refined: dict[int, NDArray[np.float64]] = {}  # watched BBs' points from the latest window
        self._shift = np.zeros(2)  # the latest frame's shift of the watched BBs from their predicted pixels
        self._motion_offset = np.zeros(2)  # what the sliding adjustments moved the poses' isocenter, summed
        self._scatter_limit_mm = max(WATCH_SCATTER_MM, 2.0 * self.opt.jitter_mm)

    def take(self, index: int, frame: NDArray[Any] | None) -> None:
        """Scan frame ``index``; indices jumped over are projections that were not sent (detected after the scan)."""
        self.skip_to(index)
        self._next_index = index + 1
        self._process(index, int(self.image_key[index]), frame)

    def skip_to(self, index: int) -> None:
        """Frames before ``index`` that never came: projections detected after the scan."""
        for skipped in range(self._next_index, index):
            self._process(skipped, int(self.image_key[skipped]), None)
        self._next_index = max(self._next_index, index)

    # --------------------------------------------------------------- per frame
    def _process(self, index: int, key: int, frame: NDArray[Any] | None) -> None:
        if frame is not None and (key == ImageKey.DARK or key == ImageKey.FLAT):
            f = frame.astype(np.float64)
            if key == ImageKey.DARK:
                self._dark_sum = f if self._dark_sum is None else self._dark_sum + f
                self._n_dark += 1
            else:
                self._flat_sum = f if self._flat_sum is None else self._flat_sum + f
                self._n_flat += 1
                if len(self._single_flats) < 2:  # two kept as they are: the panel's noise correlation
                    self._single_flats.append(np.array(frame))
            return
        if key != ImageKey.PROJECTION:
            return
        p = len(self.candidates)
        if (
            frame is None
            or self._dark_sum is None
            or self._flat_sum is None
            or (self._deferred and self.plan.predicted)
        ):
            # a predicted search of a frame depends on the frames before it: after one is missing, the rest are
            # searched after the scan too
            self.candidates.append(None)
            self.floors.append(np.nan)
            self._deferred.append(p)
            self.bbs_per_frame.append(-1)
            if not self._behind_warned:
                self._behind_warned = True
                why = (
                    "no dark and flat frames came before the first projection"
                    if self._dark_sum is None or self._flat_sum is None
                    else f"more than {self.settings.max_pending} frames were waiting"
                )
                self._warn(
                    "fell_behind",
                    index,
                    index,
                    f"live calibration is not following frame {index} on: {why}; "
                    "those frames are detected from the file after the scan (the geometry comes later)",
                )
            return
        if self._detector is None:
            dark = (self._dark_sum / self._n_dark).astype(np.float32)
            flat = (self._flat_sum / self._n_flat).astype(np.float32)
            pair = (self._single_flats[0], self._single_flats[1]) if len(self._single_flats) == 2 else None
            self._detector = frame_detector(dark, flat, self.d_px, self.opt, pair)
        t = time.perf_counter()
        searched = cast(list[NDArray[np.float64]], self.candidates)  # none deferred yet: every one searched
        found = self.plan.search(self._detector, frame, self.plan.windows(p, searched, np.array(self.floors)))
        self.detect_s += time.perf_counter() - t
        c = found.records
        self.candidates.append(c)
        self.floors.append(found.floor)
        if self._deferred:  # frames are missing before this one: follow no more, warn no more
            self.bbs_per_frame.append(-1)
            return
        view = self.nominal[index : index + 1]
        links = self.linker.step(p, c, view)
        self._watch(index, p, c, links, view)

    def _watch(self, index: int, p: int, c: NDArray[np.float64], links: FrameLinks, view: ViewGeometry) -> None:
        """Per frame: BBs found, warnings. A track followed for ``watch_after`` frames whose 3-D point (its rays
        through the nominal geometry) is no known BB's becomes a watched BB; from then on every watched BB is
        predicted in each frame (its point through the view, moved by the frame's common shift) and assigned to the
        frame's BB-like blobs, so a BB keeps its identity whatever the 2-D tracks do where BBs cross."""
        s = self.settings
        n_bbs = int(links.continued.size + links.started.size)
        self.bbs_per_frame.append(n_bbs)
        self.emit(
            "marks", (index, np.vstack([links.uv.reshape(-1, 2), links.started_uv.reshape(-1, 2)]).round(2).tolist())
        )
        metrics = {"bbs": float(n_bbs), "frame": float(index)}
        message = f"frame {index}: {n_bbs} BBs"
        if n_bbs < s.min_bbs:  # a view with too few BBs (once per run of such frames)
            if self._few_since is None:
                self._few_since = index
                self._warn(
                    "few_bbs",
                    index,
                    index,
                    f"frame {index} shows {n_bbs} BB(s); a view needs {s.min_bbs} to be "
                    "calibrated from its own (more BBs where this part of the orbit looks, or it is bridged)",
                )
        else:
            self._few_since = None
        blobs = np.concatenate([links.uv, links.started_uv])
        claimed = np.zeros(len(blobs), bool)  # blobs that are a watched BB in this frame
        keys = tuple(self._watched)
        watched = [self._watched[t] for t in keys]
        if watched:
            # once per frame: the window's refined point, else a least-squares solve of the BB's rays
            points = np.array([self._refined[t] if t in self._refined else w.point() for t, w in zip(keys, watched)])
            pred = view.project(points)[0]
            # searched around the last frame's shift: the points, triangulated through the nominal views, and the
            # orbit's errors put the BBs off their nominal projection by a shift that drifts along the orbit
            idx, _ = match_frame(
                pred + self._shift, blobs, self.tracking.search_px, self.tracking.gate_px, self.tracking.residual_px
            )
            hit = idx >= 0  # where a missing BB should be: its point through the view, moved by the frame's shift
            if hit.sum() >= 2:
                self._shift = np.median(blobs[idx[hit]] - pred[hit], axis=0)
            tracks = np.concatenate([links.continued, links.started])
            followed = {int(t): j for j, t in enumerate(links.continued.tolist())}
            for k, w in enumerate(watched):  # not where its point says but still on its 2-D track: the same BB
                j = followed.get(w.track, -1)
                if idx[k] < 0 and j >= 0 and j not in idx:
                    idx[k] = j
            self._through_pose(view, points, blobs, idx, c, np.array([w.look for w in watched]))
            hit = idx >= 0
            claimed[idx[hit]] = True
            for k in np.flatnonzero(hit).tolist():
                watched[k].track = int(tracks[idx[k]])
            aligned = pred + self._shift
            origin, direction = view_rays(view, blobs) if len(blobs) else (None, None)
            matched = (
                np.where((idx >= 0)[:, None], blobs[np.maximum(idx, 0)], np.nan)
                if len(blobs)
                else np.full((len(watched), 2), np.nan)
            )
            pose = self._frame_pose(index, view, points, matched)
            if pose is not None:
                self.window.add(index, keys, matched, pose.state)
                if self.window.due:
                    self._refined.update(
                        self.window.refine(
                            self.nominal, dict(zip(keys, points)), loss_px=max(1.5 * self._noise_px(), 0.05)
                        )
                    )
                    self._motion_offset += self.window.moved_mm  # the jump watch's series carried across it
                metrics.update(
                    rpe_mm=pose.rpe_mm,
                    rpe_mean_mm=float(np.mean(self.rpe_mm)),
                    predicted_px=pose.predicted_px,
                    misfit_px=pose.misfit_px,
                )
                message += f", RPE {pose.rpe_mm:.3f} mm, predicted {pose.predicted_px:.2f} px"
            panel = view.panel
            margin = 0.5 * self.d_px + 1.0 + s.edge_margin_px
            # the scatter test only while some BB's point still takes rays (each watched BB's point costs a solve)
            reference = self._scatter_reference_mm() if any(w.count < POINT_RAYS for w in watched) else None
            scattered: list[int] = []
            for t, w, j, uv in zip(keys, watched, idx.tolist(), aligned):
                if j >= 0 and origin is not None and direction is not None:  # j >= 0: there are blobs
                    w.add_ray(origin, direction[j])
                    if w.count <= POINT_RAYS and not self._one_point(w, reference):
                        scattered.append(t)  # its rays meet at no point: not one BB's
                        continue
                    if w.warned:
                        self._warn(
                            "bb_found",
                            index,
                            w.missing_since or index,
                            f"frame {index}: the BB lost since frame "
                            f"{w.missing_since} is found again at ({blobs[j, 0]:.0f}, {blobs[j, 1]:.0f}) px",
                            uv=(float(blobs[j, 0]), float(blobs[j, 1])),
                        )
                    w.last_frame, w.last_uv = index, (float(blobs[j, 0]), float(blobs[j, 1]))
                    w.missing_since, w.warned, w.outside = None, False, False
                    continue
                inside = bool(
                    np.isfinite(uv).all()
                    and margin <= uv[0] <= panel.cols - 1 - margin
                    and margin <= uv[1] <= panel.rows - 1 - margin
                )
                if not inside:
                    if not w.outside and w.last_frame >= index - 2:
                        self._warn(
                            "bb_left_fov",
                            index,
                            index,
                            f"frame {index}: the BB last at ({w.last_uv[0]:.0f}, "
                            f"{w.last_uv[1]:.0f}) px left the field of view",
                            uv=w.last_uv,
                        )
                    w.outside, w.missing_since, w.warned = True, None, False
                    continue
                w.outside = False
                if w.missing_since is None:
                    w.missing_since = index
                if index - w.missing_since + 1 >= DISTORTED_FRAMES:
                    self._distorted(index, w.missing_since, c, uv)
                if not w.warned and index - w.missing_since + 1 > s.lost_frames:
                    w.warned = True
                    self._warn(
                        "bb_lost",
                        index,
                        w.missing_since,
                        f"frame {index}: the BB last seen at ({w.last_uv[0]:.0f}, {w.last_uv[1]:.0f}) px in frame "
                        f"{w.last_frame} is missing since frame {w.missing_since} where it should be visible near "
                        f"({uv[0]:.0f}, {uv[1]:.0f}) px (over metal, bone or another BB, or fallen off?)",
                        uv=(float(uv[0]), float(uv[1])),
                    )
            for t in scattered:
                del self._watched[t]
                self._refined.pop(t, None)
        self._new_bbs(links, view, claimed[: links.continued.size])
        self.emit("progress", ("live-calibration", p + 1, self.n_projections, message, metrics))

    def _through_pose(
        self,
        view: ViewGeometry,
        points: NDArray[np.float64],
        blobs: NDArray[np.float64],
        idx: NDArray[np.intp],
        c: NDArray[np.float64],
        looks: NDArray[np.float64],
    ) -> None:
        """A second look for the watched BBs not found (``idx`` -1, filled in place): through this frame's pose, fitted
        to the BBs found, each is predicted with the rotation and magnification the frame's common shift leaves
        out (a BB far from the others in depth drifts off its shifted prediction by several pixels along the
        orbit, and was reported lost while in view), and takes the nearest free blob within the gate that looks
        like the watched BBs (candidates ``c``, the BBs' median records ``looks``: not noise over metal)."""
        if len(blobs) == 0 or (idx >= 0).sum() < 4 or (idx >= 0).all():
            return
        matched = np.where((idx >= 0)[:, None], blobs[np.maximum(idx, 0)], np.nan)
        pose = fit_frame_pose(view, points, matched, self._noise_px(), self._last_pose)
        if pose is None:
            return
        again = ViewModel(view).geometry(pose.state).project(points)[0]
        free = np.ones(len(blobs), bool)
        free[idx[idx >= 0]] = False
        for k in np.flatnonzero(idx < 0):
            d = np.where(free, np.linalg.norm(blobs - again[k], axis=1), np.inf)
            j = int(np.argmin(d))
            if d[j] > self.tracking.gate_px:
                continue
            if like_the_others(_record_at(c, blobs[j])[None], looks):
                idx[k], free[j] = j, False

    def _frame_pose(
        self, index: int, view: ViewGeometry, xyz: NDArray[np.float64], uv: NDArray[np.float64]
    ) -> FramePose | None:
        """The frame's pose from its watched BBs (:func:`calib.framepose.fit_frame_pose`); feeds the running RPE,
        the centroid noise and the jump watch, which warns when the object moved."""
        noise_px = self._noise_px()
        pose = fit_frame_pose(view, xyz, uv, noise_px, self._last_pose)
        if pose is None:
            return None
        self._last_pose = pose.state
        self.rpe_mm.append(pose.rpe_mm)
        if np.isfinite(pose.misfit_px):
            self._misfits.append(pose.misfit_px)
        if not pose.misfit_px <= WATCH_MISFIT * noise_px:  # a doubtful pose (a wrong or rough detection)
            return pose
        step = self._steps.add(index, pose.motion_mm - self._motion_offset)
        if step is not None:
            self._warn(
                "object_moved",
                index,
                step.since_frame,
                f"frame {index}: where each frame's fitted pose puts the isocenter jumped by {step.size_mm:.1f} mm "
                f"at frame {step.since_frame} and stayed ({step.sigmas:.0f} sigma of its "
                "frame-to-frame noise): the object "
                "moved on the table? A move of the object with its BBs is calibrated away; if it moved against "
                "its BBs (loose tape, soft tissue), stop and scan again",
            )
        return pose

    def _noise_px(self) -> float:
        """Centroid noise from the recent frames' pose misfits (0.15 px before there are any)."""
        return float(np.median(self._misfits)) if len(self._misfits) >= 5 else 0.15

    def linked(self) -> NDArray[np.float64] | None:
        """The 2-D tracks of every projection, linked as the offline calibration links them; None when frames
        were left for after the scan (following stopped there)."""
        if self._deferred:
            return None
        return self.linker.fragments(len(self.candidates), self.tracking.min_fragment)

    def _new_bbs(self, links: FrameLinks, view: ViewGeometry, claimed: NDArray[np.bool_]) -> None:
        """Tracks followed for ``watch_after`` frames become watched BBs (their whole history of rays), unless their
        blob in this frame is a watched BB's (``claimed``, per continued track) or their point lies within two BB
        diameters of a watched BB's (a BB followed again by a new track after a crossing: its few rays place it
        poorly in depth, so the frame's assignment decides first), or their blobs do not look like the watched BBs'
        (:func:`calib.track.like_the_others`, once three are watched)."""
        known = np.array([w.point() for w in self._watched.values()]).reshape(-1, 3)
        for t, taken in zip(links.continued.tolist(), claimed.tolist(), strict=True):
            if t in self._tracks_seen or self.linker.store.count[t] < self.settings.watch_after:
                continue
            self._tracks_seen.add(t)
            if taken:
                continue
            w = _Watched()
            records = []
            for frame_p, ids, uv in self.linker.store.obs:
                hit = np.flatnonzero(ids == t)
                if hit.size:
                    f = int(self._proj_index[frame_p])
                    o, d = view_rays(self.nominal[f : f + 1], uv[hit])
                    w.add_ray(o, d[0])
                    w.last_frame, w.last_uv = f, (float(uv[hit[0], 0]), float(uv[hit[0], 1]))
                    cands = self.candidates[frame_p]
                    if cands is not None:  # always: a frame's blobs are tracked only when it has candidates
                        records.append(_record_at(cands, uv[hit[0]]))
            x = w.point()
            if known.size and np.linalg.norm(known - x, axis=1).min() < 2.0 * self.diameter_mm + 5.0:
                continue  # a BB already watched, followed by another track
            if not self._one_point(w, self._scatter_reference_mm()):
                continue  # its rays meet at no point: a track that followed two BBs, or a structure
            w.look = np.nanmedian(np.array(records), axis=0)
            if len(self._watched) >= 3 and not like_the_others(
                w.look, np.array([v.look for v in self._watched.values()])
            ):
                continue  # round for a few frames, but not like the BBs: a structure of the object
            w.track = t
            self._watched[t] = w
            known = np.vstack([known, x])

    def _scatter_reference_mm(self) -> float | None:
        """The watched BBs' median ray scatter (mm); None while fewer than three are watched."""
        scatter = [w.scatter_mm() for w in self._watched.values()]
        return float(np.median(scatter)) if len(scatter) >= 3 else None

    def _one_point(self, w: _Watched, reference_mm: float | None) -> bool:
        """Whether the rays of ``w`` meet at one point as a BB's do: within :data:`WATCH_SCATTER_MM` and
        :data:`WATCH_SCATTER_RATIO` times the watched BBs' median scatter ``reference_mm``."""
        scatter = w.scatter_mm()
        return scatter <= self._scatter_limit_mm and (
            reference_mm is None or scatter <= WATCH_SCATTER_RATIO * reference_mm
        )

    def _distorted(self, index: int, since: int, c: NDArray[np.float64], uv: NDArray[np.float64]) -> None:
        """Warn (once per lost_frames frames) when a blob lies where a BB missing since frame ``since`` should be but
        is not ball-like."""
        if not len(c) or index - self._last_distorted <= self.settings.lost_frames:
            return
        d = np.linalg.norm(c[:, :2] - uv, axis=1)
        near = (d < 2.0 * self.tracking.gate_px) & ~ball_like(c, self.tracking)
        if near.any():
            self._last_distorted = index
            self._warn(
                "bb_distorted",
                index,
                since,
                f"frame {index}: the blob where a BB missing since frame {since} "
                f"should be, near ({uv[0]:.0f}, {uv[1]:.0f}) px, does not look like a BB (over metal or bone, or "
                "merged with another BB)",
                uv=(float(uv[0]), float(uv[1])),
            )

    def _warn(
        self, kind: WarningKind, frame: int, since: int, message: str, uv: tuple[float, float] | None = None
    ) -> None:
        self.emit("warning", LiveWarning(kind, int(frame), int(since), message, uv))
