"""Where a calibration searches each projection for BBs: after the first frames, only round the BBs a few frames
before it found (the predicted search), and the whole frame when one of them is missing there and every few frames.

The peaks of a frame are refined at full resolution one by one, which is most of a frame's detection time; an
object full of structure offers hundreds of peaks, of which a few are BBs. Searching round the BBs already found
skips the rest (peaks weaker than the last whole search kept are left out, as it would have left them). Frames
are searched on worker threads ahead of the one whose results are taken, so frame ``n``'s windows come from frame
``n - LAG``: a fixed lag keeps the candidates independent of the threads' timing. This is the default;
``bb_search="full"`` searches every frame whole.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from calib.detect import FrameDetector, FrameSearch
from calib.track import TrackingSettings, ball_like

#: frame ``n`` is searched round the BBs of frame ``n - LAG`` (as many frames are searched at once)
LAG = 3
#: every FULL_EVERY-th frame is searched whole: a BB that comes into view (over the panel's edge, from behind
#: metal, out of an overlap) is found within the gap the frame-to-frame linking bridges (``max_gap``)
FULL_EVERY = 4
#: a blob counts as a BB being followed when it was seen in this many frames in a row; one that must be found
#: again (else the frame is searched whole). Round structure of the object seen for a frame or two gets a window
#: but is not missed
FOLLOWED_FRAMES = 3


@dataclass(frozen=True)
class Windows:
    """Where one frame is searched: squares of half-side ``reach_px`` round ``centres`` (K, 2) (col, row); the
    ``followed`` ones hold BBs followed so far, each of which must be found again."""

    centres: NDArray[np.float64]
    reach_px: NDArray[np.float64]
    followed: NDArray[np.bool_]
    floor: float  # peaks scoring less are not kept: the last whole search's weakest (it kept the most it may)


@dataclass(frozen=True)
class SearchPlan:
    """The predicted search of one scan: frame ``n`` is searched round the BBs of frame ``n - LAG``, and of the
    frames before it back to the last searched whole, each as far as a BB can move since."""

    tracking: TrackingSettings
    predicted: bool = True  # False: every frame is searched whole

    @classmethod
    def for_scan(
        cls, diameter_px: float, motion_px: float, jitter_px: float, bb_search: str = "predicted"
    ) -> SearchPlan:
        """The plan for BBs of ``diameter_px`` moving ``motion_px`` per frame (the nominal orbit's, 95th
        percentile) with the orbit's allowed ``jitter_px``; ``bb_search`` as the calibration options say."""
        tracking = TrackingSettings(diameter_px=diameter_px, motion_px=motion_px, jitter_px=jitter_px)
        return cls(tracking, predicted=bb_search == "predicted")

    def search(self, detector: FrameDetector, frame: NDArray[Any], windows: Windows | None) -> FrameSearch:
        """The frame's candidates: in its ``windows`` when every BB followed there is found again (the floor
        then NaN: the frame was not searched whole), else in the whole frame."""
        if windows is not None:
            found = detector.search(frame, windows.centres, windows.reach_px, windows.floor)
            if self.found_all(windows, found.records):
                return FrameSearch(found.records, float("nan"))
        return detector.search(frame)

    def reach_px(self, frames: int) -> float:
        """How far a BB may move in ``frames`` frames: the nominal motion, the allowed jitter and a diameter."""
        s = self.tracking
        return frames * s.motion_px + s.jitter_px + s.diameter_px

    def whole(self, n: int) -> bool:
        """Whether frame ``n`` is searched whole whatever the frames before it hold (the first frames, every
        FULL_EVERY-th, all of them with ``bb_search="full"``): it may be searched before them."""
        return not self.predicted or n < LAG or n % FULL_EVERY == 0

    def windows(self, n: int, cands: list[NDArray[np.float64]], floors: NDArray[np.float64]) -> Windows | None:
        """Where frame ``n`` is searched, from the candidates found so far and the floors of the frames searched
        whole (NaN for the others; both final up to ``n - LAG``); None: search it whole."""
        if self.whole(n):
            return None
        whole = np.flatnonzero(np.isfinite(floors[: n - LAG + 1]))
        floor = float(floors[whole[-1]]) if len(whole) else 0.0
        centres = self._ball_like(cands[n - LAG])
        earlier = [self._ball_like(cands[n - LAG - j]) for j in range(1, min(FULL_EVERY, n - LAG + 1))]
        reach = np.full(len(centres), self.reach_px(LAG))
        followed = np.ones(len(centres), bool)
        for j, before in enumerate(earlier[: FOLLOWED_FRAMES - 1], start=1):
            followed &= _within(centres, before, self.reach_px(j))
        if followed.sum() < 0.75 * len(centres):  # the blobs jump between frames: the orbit jitters, search whole
            return None
        # BBs that a frame before saw (one of them was searched whole) and frame n - LAG did not
        for j, before in enumerate(earlier, start=1):
            new = before[~_within(before, centres, self.reach_px(j))]
            centres = np.concatenate([centres, new])
            reach = np.concatenate([reach, np.full(len(new), self.reach_px(LAG + j))])
            followed = np.concatenate([followed, np.zeros(len(new), bool)])
        return Windows(centres, reach, followed, floor) if len(centres) else None

    def found_all(self, windows: Windows, c: NDArray[np.float64]) -> bool:
        """Whether each followed BB's window holds a ball-like candidate of ``c`` of its own (else a BB was lost
        there, or jumped out of its window, perhaps into another's, and the frame is searched whole)."""
        f = windows.followed
        centres, bbs = windows.centres[f], self._ball_like(c)
        if not len(centres):
            return True
        if len(bbs) < len(centres):
            return False
        far = _apart(centres, bbs)
        inside = far <= windows.reach_px[f][:, None]
        rows, cols = linear_sum_assignment(np.where(inside, far, 1e9))
        return bool(inside[rows, cols].all())

    def _ball_like(self, c: NDArray[np.float64]) -> NDArray[np.float64]:
        if not len(c):
            return np.zeros((0, 2))
        return np.ascontiguousarray(c[ball_like(c, self.tracking), :2])


def _within(
    points: NDArray[np.float64], others: NDArray[np.float64], reach_px: float | NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Which ``points`` have one of ``others`` within ``reach_px`` (each point's, or one for all) in each
    direction."""
    if not len(others):
        return np.zeros(len(points), bool)
    return np.asarray((_apart(points, others) <= np.reshape(reach_px, (-1, 1))).any(axis=1))


def _apart(points: NDArray[np.float64], others: NDArray[np.float64]) -> NDArray[np.float64]:
    """How far each of ``points`` lies from each of ``others`` ``(K, M)``: the larger of the column and row
    distances (the windows are squares)."""
    return np.asarray(np.abs(points[:, None, :] - others[None, :, :]).max(axis=-1))
