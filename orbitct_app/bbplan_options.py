"""The options of a BB placement plan, in one place: names, units, limits and defaults.

``orbitct plan bbs`` makes its options from :class:`BBPlanOptions`, the REST service's plan request (``POST
/plans/bbs``) extends it, and :class:`orbitct_app.bbplan.BBPlanRequest` (the planner's input) holds it, so the same plan gets
the same answer everywhere. Where the object's surface comes from (a file here, an upload or a reconstruction
there) is each interface's own. This module stays light, so that the command starts quickly.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from orbitct.options import option_problems

#: the most BBs a plan places or tries
MAX_BBS = 40
#: the orbit's expected motion errors a plan allows for (error profiles)
MOTION_ERRORS = ("none", "bench")


class KeepOutZone(BaseModel):
    """A patch of the object's surface without BBs: polar angles (deg, counterclockwise from +x; through 0 when
    ``angle_to_deg < angle_from_deg``; 0 to 360: the whole turn) between two heights (mm)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)  # floats (numpy's are floats too)
    angle_from_deg: float = Field(ge=0.0, lt=360.0)
    angle_to_deg: float = Field(
        ge=0.0, le=360.0, description="not the same angle as angle_from_deg (only 0 to 360 makes the whole turn)"
    )
    z_min_mm: float = Field(ge=-1000.0, le=1000.0, description="below z_max_mm")
    z_max_mm: float = Field(ge=-1000.0, le=1000.0)

    @model_validator(mode="after")
    def _a_patch(self) -> KeepOutZone:
        if not self.z_min_mm < self.z_max_mm:
            raise ValueError(f"z_min_mm ({self.z_min_mm:g}) must be below z_max_mm ({self.z_max_mm:g})")
        if self.angle_from_deg == self.angle_to_deg % 360.0 and self.angle_to_deg - self.angle_from_deg != 360.0:
            raise ValueError(
                f"angle_from_deg and angle_to_deg ({self.angle_from_deg:g}) make no patch; the whole turn is 0 to 360"
            )
        return self


class BBPlanOptions(BaseModel):
    """What to plan: the object and default orbit of an experiment, the orbit, the panel, how many BBs (or the
    accuracy to reach with as few as possible), where not to put them, and the detection's centroid noise."""

    # not strict: Python's numbers (numpy's too) are taken as they are; the REST request (JSON) is strict
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    experiment: Literal["A", "B", "C"] = Field(description="the object (its surface, metal, BB size) and its orbit")
    orbit: str | None = Field(
        None, max_length=40, pattern=r"^[a-z_-]+$", description="orbit kind (default: the experiment's)"
    )
    frames: int | None = Field(None, ge=2, le=5000, description="projections (default: the orbit's)")
    bbs: int = Field(8, ge=4, le=MAX_BBS, description="BBs to place")
    target_px: float | None = Field(
        None,
        gt=0.0,
        le=10.0,
        description="instead of a count of BBs: the fewest whose planned placement predicts at most this error "
        "(px) in every view",
    )
    max_bbs: int = Field(20, ge=4, le=MAX_BBS, description="with a target error: the most BBs to try")
    keep_out: list[KeepOutZone] = Field(default_factory=list, max_length=20, description="patches without BBs")
    detector_px: int = Field(768, ge=8, le=4096, description="pixels across the square panel")
    errors: Literal["none", "bench"] = Field(
        "none",
        description="the orbit's expected motion errors (an error profile): a BB counts in a view only where it "
        "stays usable in three samples of it",
    )
    noise_px: float = Field(
        0.1, gt=0.0, le=5.0, description="centroid noise of the BB detection (a calibration reports it)"
    )
    seed: int = Field(0, ge=0, le=2**32 - 1, description="the search's random start")
    surface_threshold_per_mm: float | None = Field(
        None, gt=0.0, le=10.0, description="with a volume as the surface: its object/air threshold (default: Otsu's)"
    )

    @field_validator("experiment", mode="before")
    @classmethod
    def _upper(cls, value: Any) -> Any:
        return value.upper() if isinstance(value, str) else value


def checked_plan_options(**options: Any) -> BBPlanOptions:
    """:class:`BBPlanOptions` from keyword ``options``, or ValueError naming each option that is wrong."""
    try:
        return BBPlanOptions.model_validate(options)
    except ValidationError as exc:
        raise ValueError(option_problems(exc, BBPlanOptions)) from None
