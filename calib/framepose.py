"""One view's pose while the scan runs, and the jump of the object on the table.

Live calibration knows each watched BB's 3-D point (its rays through the nominal geometry) and, per frame, where
the watched BBs are. :func:`fit_frame_pose` fits the frame's rigid correction to them (six parameters, the
points held) and gives the frame's RPE (the paper's figure), its residual RMS and the predicted error of its
geometry over the field of view from the pose's covariance, and how far the fit moved the isocenter's projection
from the nominal view's. :class:`StepWatch` follows that shift frame by frame: orbit errors are smooth plus
frame-to-frame noise, so a shift that jumps and stays there means the object (with its BBs) moved on the table.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calib.model import ViewModel, ViewState, all_finite
from calib.quality import fit_rigid_poses, pose_predicted_px, view_misfit_px
from calib.rays import rpe_per_frame
from orbitct.geometry import ViewGeometry

#: a BB whose detection misses the fitted pose by more than this many centroid noises (and OUTLIER_MIN_PX) is
#: taken for a wrong assignment and the pose fitted without it, at most MAX_DROPPED times, keeping four BBs
OUTLIER_NOISES = 6.0
OUTLIER_MIN_PX = 1.0
MAX_DROPPED = 2


#: a frame of the jump watch's baseline off its curve by more than this many sigmas is left out of the curve
OUTLIER_SIGMAS = 4.0


@dataclass(frozen=True)
class FramePose:
    """The rigid correction of one frame fitted to its watched BBs, and how well it is known."""

    state: ViewState
    n_bbs: int
    rpe_mm: float
    misfit_px: float  # residual RMS corrected for the six pose parameters
    predicted_px: float  # RMS over field-of-view points of the projection error the pose's covariance implies

    motion_mm: NDArray[np.float64]  # how far the fit moved the isocenter's projection (:func:`isocenter_motion_mm`)


def fit_frame_pose(
    view: ViewGeometry,
    xyz: NDArray[np.float64],
    uv: NDArray[np.float64],
    noise_px: float,
    start: ViewState | None = None,
) -> FramePose | None:
    """Pose of the single view ``view`` fitted to BBs ``xyz`` (K, 3) seen at ``uv`` (K, 2; NaN = not seen), from
    ``start`` (the previous frame's, or none); None with fewer than four BBs (no redundancy to judge by)."""
    seen = all_finite(uv) & all_finite(xyz)
    if seen.sum() < 4:
        return None
    model = ViewModel(view)
    for attempt in range(MAX_DROPPED + 1):
        xyz_s, uv_s = xyz[seen], uv[None, seen]
        st = fit_rigid_poses(model, start.copy() if start is not None else model.identity(), xyz_s, uv_s)
        if not (np.isfinite(st.R).all() and np.isfinite(st.t).all()):
            return None
        geometry = model.geometry(st)
        residual = np.linalg.norm(geometry.project(xyz_s)[0] - uv_s[0], axis=1)
        worst = int(np.argmax(residual))
        if (
            attempt == MAX_DROPPED
            or seen.sum() <= 4
            or residual[worst] <= max(OUTLIER_NOISES * noise_px, OUTLIER_MIN_PX)
        ):
            break
        seen[np.flatnonzero(seen)[worst]] = False  # a blob taken for this BB that is another: fitted without it
    return FramePose(
        state=st,
        motion_mm=isocenter_motion_mm(view, geometry)[0],
        n_bbs=int(seen.sum()),
        rpe_mm=float(rpe_per_frame(geometry, uv_s, xyz_s)[0]),
        misfit_px=float(view_misfit_px(model, st, xyz_s, uv_s)[0]),
        predicted_px=float(pose_predicted_px(model, st, xyz_s, uv_s, noise_px)[0]),
    )


def isocenter_motion_mm(nominal: ViewGeometry, corrected: ViewGeometry) -> NDArray[np.float64]:
    """Per view ``(N, 2)``, how far the corrected view moves the isocenter's projection from where the nominal view
    puts it, along the panel's columns and rows, in mm at the isocenter: the motion the detector sees best (a pose's
    depth along the beam is poorly known). A fixed point, not the BBs' mean: the BBs seen differ from their nominal
    projections by different amounts, so the mean of those seen would jump whenever one is hidden or found."""
    isocenter = np.zeros((1, 3))
    shift_px = corrected.project(isocenter)[:, 0] - nominal.project(isocenter)[:, 0]
    panel = nominal.panel
    return shift_px * np.array([panel.pitch_col, panel.pitch_row]) * (nominal.sod() / nominal.sdd)[:, None]


def _curve(
    A: NDArray[np.float64], y: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Least-squares coefficients of ``y`` on the design ``A``, the residuals and their robust sigma per column
    (1.4826 MAD, at least 1e-3)."""
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    resid = y - A @ coef
    sigma = 1.4826 * np.median(np.abs(resid - np.median(resid, axis=0)), axis=0) + 1e-3
    return coef.astype(np.float64), resid, sigma


@dataclass(frozen=True)
class Step:
    """A jump of the corrections: the first frame after it, its size (mm) and how many noise sigmas that is."""

    since_frame: int
    size_mm: float
    sigmas: float


class StepWatch:
    """Finds a jump that stays in a series of per-frame motions (:attr:`FramePose.motion_mm`).

    A parabola is fitted per component to the ``baseline`` frames before the latest ``m`` (m = 4, 8 and 16 are
    tried: a large jump shows in 4 frames, a jump the size of the frame-to-frame noise needs more; frames off the
    curve by more than :data:`OUTLIER_SIGMAS` are left out and it is fitted again; nothing is judged before there
    are ``baseline`` frames); the median of the latest ``m`` against the parabola's extrapolation, in units of its
    standard error (the median's and the extrapolation's, from the baseline's scatter), must exceed ``sigmas`` over
    the components together (root sum of squares), and the jump be at least ``min_mm``. After a jump the baseline
    starts again behind it."""

    def __init__(
        self,
        baseline: int = 80,
        sigmas: float = 8.0,
        min_mm: float = 1.0,
        recent: tuple[int, ...] = (4, 8, 16),
        max_gap: int = 5,
    ) -> None:
        self.baseline, self.sigmas, self.min_mm, self.recent, self.max_gap = baseline, sigmas, min_mm, recent, max_gap
        self._frames: deque[int] = deque(maxlen=baseline + max(recent))
        self._values: deque[NDArray[np.float64]] = deque(maxlen=baseline + max(recent))

    def add(self, frame: int, motion_mm: NDArray[np.float64]) -> Step | None:
        """Add one frame's motion; the jump it completes, if any. After more than ``max_gap`` frames without one the
        baseline starts again (a curve is not extrapolated across a gap)."""
        if self._frames and frame - self._frames[-1] > self.max_gap:
            self._frames.clear()
            self._values.clear()
        self._frames.append(int(frame))
        self._values.append(np.asarray(motion_mm, float))
        values = np.array(self._values)
        frames = np.array(self._frames, float)
        for m in self.recent:
            if len(values) - m < self.baseline:  # a curve through fewer frames bends with their noise
                continue
            base_n = self.baseline
            base = slice(len(values) - m - base_n, len(values) - m)
            x = frames[base] - frames[base].mean()
            A = np.column_stack([np.ones(base_n), x, x * x])
            coef, resid, sigma = _curve(A, values[base])
            inlier = (np.abs(resid) <= OUTLIER_SIGMAS * sigma).all(1)  # a wrong pose would bend the curve: fitted again
            if not inlier.all():
                A = A[inlier]
                coef, resid, sigma = _curve(A, values[base][inlier])
            xr = frames[-m:] - frames[base].mean()
            line = np.column_stack([np.ones(m), xr, xr * xr]) @ coef
            jump = np.median(values[-m:] - line, axis=0)
            # standard error: the median of m values (1.25 sigma / sqrt(m)) and the curve extrapolated to them
            at = np.array([1.0, xr.mean(), (xr * xr).mean()])
            se = sigma * np.sqrt(1.2533**2 / m + float(at @ np.linalg.solve(A.T @ A, at)))
            z = jump / se
            score = float(np.sqrt(np.sum(z**2)))
            size = float(np.linalg.norm(jump))
            if score <= self.sigmas or size < self.min_mm:
                continue
            # the first of the latest frames that went at least half way
            along = (values[-m:] - line) @ jump / float(jump @ jump)
            since = int(frames[-m:][int(np.argmax(along > 0.5))])
            while len(self._frames) > m:  # the baseline starts again behind the jump
                self._frames.popleft()
                self._values.popleft()
            return Step(since, size, score)
        return None


__all__ = ["FramePose", "Step", "StepWatch", "fit_frame_pose", "isocenter_motion_mm"]
