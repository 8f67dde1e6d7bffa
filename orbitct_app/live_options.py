"""The options of calibrating a scan while it runs, in one place.

``orbitct scan --calibrate live`` makes its options from :class:`LiveCalibrationOptions`, the REST service's scan
request (``POST /scans``) extends it, and :class:`orbitct_app.live_calibration.LiveCalibrationSubscriber` is
made from it. This module stays light (no calibration imported) so that ``orbitct scan`` starts quickly.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from orbitct.livewarnings import ABORT_KINDS, AbortKind


class LiveCalibrationOptions(BaseModel):
    """Whether to follow the BBs while the frames arrive, their size, and the warnings that stop the scan."""

    # not strict: Python's numbers (numpy's too) are taken as they are; the REST request (JSON) is strict
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    calibrate: Literal["none", "live"] = Field(
        "none",
        description="live: detect and follow the BBs while the frames arrive, warn during the scan, and write the "
        "calibrated geometry as soon as the last frame is in (as orbitct calibrate would)",
    )
    bb_diameter_mm: float | None = Field(
        None, gt=0.1, le=50.0, description="BB diameter for live calibration (default on the twins: their BBs)"
    )
    abort_on: list[AbortKind] = Field(
        default_factory=list,
        max_length=len(ABORT_KINDS),
        description="live calibration warnings that stop the scan safely (axes halted, X-rays off, file aborted)",
    )
    lost_frames: int = Field(
        10, ge=1, le=10_000, description="warn when a followed BB is missing for more than this many frames"
    )

    @model_validator(mode="after")
    def _live_only(self) -> LiveCalibrationOptions:
        if self.abort_on and self.calibrate != "live":
            raise ValueError("abort_on needs calibrate: live")
        return self
