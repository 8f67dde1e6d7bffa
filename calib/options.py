"""The options of a calibration: their defaults, limits and the check that names what is wrong."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from calib.errors import OptionError
from calib.model import INTRINSICS

METHODS = ("bundle", "paper")
DEFAULT_JITTER_MM = 3.0
RECOVERY_JITTER_MM = (8.0, 15.0, 25.0)  # tracking allowances tried in turn when the BBs are not followed


@dataclass
class CalibrationOptions:
    """Tunable settings of :func:`calibrate_scan` (pass as keyword options)."""

    iterations: int | None = None  # paper: alternations (default 3); bundle: max LM iterations (default 30)
    intrinsics: str = "fixed"  # bundle only: "fixed", "sdd" or "sdd+pp"
    loss_scale_px: float | None = None  # Huber threshold (px); default: 1.5 x the measured centroid noise
    min_bbs_per_view: int = 3  # a view with fewer is never fitted on its own (the bundle needs 4 to call it its own)
    bridge_max_views: int = 10  # bundle: widest run of views without 4 BBs that is bridged from its neighbours
    max_predicted_px: float = 0.5  # quality check: largest predicted field-of-view error a view may have
    min_observations: int | None = None  # frames a BB must be seen in (default max(8, 5% of projections))
    diameter_mm: float | None = None  # BB diameter; default /markers@diameter_mm, else estimated
    k_sigma: float = 6.0  # detection threshold in noise standard deviations
    max_candidates: int = 128  # strongest peaks kept per frame, at least (see calib.detect.CANDIDATE_AREA_PX)
    outlier_px: float = 1.0  # bundle: detections off by more than max(this, 6 robust sigma) become NaN
    workers: int = 2  # detection threads
    seeds_uv: Any = None  # optional (K, 2) BB positions (col, row) in the first projection
    # frame-to-frame jitter of the orbit around the nominal (object scale) for tracking
    jitter_mm: float = DEFAULT_JITTER_MM
    recover: bool = True  # track again allowing larger jumps (RECOVERY_JITTER_MM) when the first result fails
    scale_bar_mm: float | None = None  # known distance between two BBs (a scale bar): sets the metric scale
    # which BBs span the scale bar (1-based, as the report numbers them); default: the one pair near its length
    scale_bar_bbs: tuple[int, int] | None = None
    # bundle: solve once more at the end, each detection weighted by how rough its background is
    weigh_detections: bool = True


def checked_options(method: str, options: dict[str, Any]) -> CalibrationOptions:
    if method not in METHODS:
        raise OptionError(f"method must be one of {METHODS}, got {method!r}")
    known = {f.name for f in fields(CalibrationOptions)}
    unknown = set(options) - known
    if unknown:
        raise OptionError(f"unknown option(s) {sorted(unknown)}; allowed are {sorted(known)}")
    opt = CalibrationOptions(**options)
    if opt.intrinsics not in INTRINSICS:
        raise OptionError(f"intrinsics must be one of {sorted(INTRINSICS)}, got {opt.intrinsics!r}")
    if method == "paper" and opt.intrinsics != "fixed":
        raise OptionError("the paper method estimates rigid poses only; use intrinsics='fixed'")
    if opt.min_bbs_per_view < 3:
        raise OptionError(f"min_bbs_per_view must be >= 3 (a rigid pose needs 3 BBs), got {opt.min_bbs_per_view}")
    if opt.diameter_mm is not None and not opt.diameter_mm > 0:
        raise OptionError(f"diameter_mm must be > 0, got {opt.diameter_mm}")
    if opt.scale_bar_mm is not None and not (np.isfinite(opt.scale_bar_mm) and opt.scale_bar_mm > 0):
        raise OptionError(f"scale_bar_mm must be a positive length in mm, got {opt.scale_bar_mm}")
    if opt.scale_bar_bbs is not None and opt.scale_bar_mm is None:
        raise OptionError("scale_bar_bbs names the BBs of a scale bar: give its length too (scale_bar_mm)")
    return opt
