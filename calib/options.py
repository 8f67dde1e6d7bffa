"""The options of a calibration, in one place: names, units, limits and defaults.

:class:`CalibrationOptions` is what :func:`calib.calibrate_scan` takes (as keyword options); ``orbitct calibrate``
makes its options from it and the REST service's request body extends it, so the same request gets the same answer
from the command line, the API and Python.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from calib.errors import OptionError
from orbitct.options import option_problems

METHODS = ("bundle", "paper")
DEFAULT_JITTER_MM = 3.0
RECOVERY_JITTER_MM = (8.0, 15.0, 25.0, 40.0, 60.0)  # tracking allowances tried in turn when the BBs are not followed
#: the allowances tried only while no smaller one has found BBs to calibrate with (frames that jump farther than
#: the BBs lie apart): where a smaller one calibrated, these could replace it with one that passes by a wrong blob
LAST_RESORT_JITTER_MM = (40.0, 60.0)
#: how far a frame may have jumped when BBs are assigned again through the calibrated views (at least; more when
#: the BBs were followed only with a larger allowance)
REASSIGN_JITTER_MM = 25.0


class CalibrationOptions(BaseModel):
    """How to calibrate a scan: method, per-view parameters, quality check, detection, tracking and scale."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    method: Literal["bundle", "paper"] = Field(
        "bundle", description="bundle: joint robust least squares; paper: the published alternation (Ma et al. 2022)"
    )
    iterations: int | None = Field(
        None, ge=1, le=200, description="paper: alternations (default 3); bundle: most LM iterations (default 30)"
    )
    intrinsics: Literal["fixed", "sdd", "sdd+pp"] = Field(
        "fixed", description="bundle: also estimate per view the source-detector distance and the piercing point"
    )
    max_predicted_px: float = Field(
        0.5, gt=0.0, le=100.0, description="quality check: the largest predicted field-of-view error a view may have"
    )
    bridge_max_views: int = Field(
        10,
        ge=0,
        le=1000,
        description="bundle: the widest run of views with fewer than 4 BBs bridged from its neighbours",
    )
    min_bbs_per_view: int = Field(
        3,
        ge=3,
        le=100,
        description="a view with fewer BBs is never fitted on its own (the bundle needs 4 to call it its own)",
    )
    diameter_mm: float | None = Field(
        None, gt=0.1, le=50.0, description="BB diameter in mm (default: the scan file's, else estimated)"
    )
    scale_bar_mm: float | None = Field(
        None,
        gt=0.0,
        le=5000.0,
        description="known distance between two BBs (a scale bar measured on the bench): sets the metric scale",
    )
    scale_bar_bbs: list[Annotated[int, Field(ge=1)]] | None = Field(
        None,
        min_length=2,
        max_length=2,
        description="which two BBs span the scale bar (numbers as in the report); default: the one pair near its length",
    )
    loss_scale_px: float | None = Field(
        None, gt=0.0, le=100.0, description="Huber threshold in px (default: 1.5 x the measured centroid noise)"
    )
    min_observations: int | None = Field(
        None, ge=2, le=1_000_000, description="frames a BB must be seen in (default: max(8, 5 % of the projections))"
    )
    k_sigma: float = Field(6.0, gt=0.0, le=100.0, description="detection threshold in noise standard deviations")
    max_candidates: int = Field(
        128, ge=1, le=100_000, description="strongest peaks kept per frame, at least (more on a larger image)"
    )
    bb_search: Literal["full", "predicted"] = Field(
        "predicted",
        description="predicted: search each frame round the BBs found 3 frames before (the whole frame every 4th "
        "frame, where one is missing, and when the blobs jump); full: search every frame whole",
    )
    outlier_px: float = Field(
        1.0, gt=0.0, le=100.0, description="bundle: detections off by more than max(this, 6 robust sigma) are dropped"
    )
    jitter_mm: float = Field(
        DEFAULT_JITTER_MM,
        gt=0.0,
        le=100.0,
        description="frame-to-frame jitter of the orbit around the nominal (object scale, mm) allowed in tracking",
    )
    recover: bool = Field(
        True,
        description="track again allowing larger jumps (8, 15, 25 mm; 40 and 60 mm where those find no BBs) when "
        "the first result fails its check",
    )
    weigh_detections: bool = Field(
        True, description="bundle: solve once more, each detection weighted by how rough its background is"
    )

    @model_validator(mode="after")
    def _consistent(self) -> CalibrationOptions:
        if self.method == "paper" and self.intrinsics != "fixed":
            raise ValueError("the paper method estimates rigid poses only; use intrinsics 'fixed'")
        if self.scale_bar_bbs is not None and self.scale_bar_mm is None:
            raise ValueError("scale_bar_bbs names the BBs of a scale bar: give its length too (scale_bar_mm)")
        if self.scale_bar_bbs is not None and self.scale_bar_bbs[0] == self.scale_bar_bbs[1]:
            raise ValueError("scale_bar_bbs: a scale bar spans two different BBs")
        return self


def checked_options(method: str, options: dict[str, Any]) -> CalibrationOptions:
    """The options of a ``method`` calibration from keyword ``options``, or OptionError naming what is wrong."""
    if method not in METHODS:
        raise OptionError(f"method: must be one of {', '.join(METHODS)}, got {method!r}")
    values = {**options, "method": method}
    if isinstance(values.get("scale_bar_bbs"), tuple):
        values["scale_bar_bbs"] = list(values["scale_bar_bbs"])
    try:
        return CalibrationOptions.model_validate(values)
    except ValidationError as exc:
        raise OptionError(option_problems(exc, CalibrationOptions)) from None
