"""Parameter models of every orbit kind (degrees at the edges), with their limits."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

MAX_TILT_DEG = 60.0
MAX_ROTATION_DEG = 720.0
MAX_FRAMES = 20000

Tilt = Annotated[float, Field(ge=-MAX_TILT_DEG, le=MAX_TILT_DEG, description="tilt (CRAN/CAUD) angle, deg")]
Rotation = Annotated[
    float, Field(ge=-MAX_ROTATION_DEG, le=MAX_ROTATION_DEG, description="rotation (LAO/RAO) angle, deg")
]


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    n_frames: int = Field(500, ge=2, le=MAX_FRAMES, description="number of projection frames")


def _nonzero(v: float, what: str) -> float:
    if v == 0:
        raise ValueError(f"{what} must be non-zero")
    return v


class CircularParams(_Params):
    """A circle (or part of one) at a fixed tilt."""

    start_deg: Rotation = 0.0
    range_deg: Rotation = 360.0
    tilt_deg: Tilt = 0.0

    @field_validator("range_deg")
    @classmethod
    def _range(cls, v: float) -> float:
        return _nonzero(v, "range_deg")


class SawtoothParams(_Params):
    """Tilt oscillating between +-amplitude at constant speed while rotating."""

    amplitude_deg: float = Field(20.0, gt=0, le=MAX_TILT_DEG, description="peak tilt, deg")
    cycles: float = Field(2.0, gt=0, le=100, description="full tilt cycles over the rotation")
    start_deg: Rotation = 0.0
    range_deg: Rotation = 360.0

    @field_validator("range_deg")
    @classmethod
    def _range(cls, v: float) -> float:
        return _nonzero(v, "range_deg")


class DCArcParams(_Params):
    """Tilted full circles plus one tilting arc at a fixed rotation (double-circle-plus-arc)."""

    n_frames: int = Field(656, ge=2, le=MAX_FRAMES, description="number of projection frames")
    circle_tilts_deg: list[Tilt] = Field(default_factory=lambda: [25.0, -25.0], min_length=1, max_length=8)
    circle_range_deg: Rotation = 360.0
    start_deg: Rotation = 0.0
    arc_start_deg: Tilt = 29.0
    arc_end_deg: Tilt = -28.0
    arc_rotation_deg: Rotation = 0.0

    @field_validator("circle_range_deg")
    @classmethod
    def _range(cls, v: float) -> float:
        return _nonzero(v, "circle_range_deg")

    @model_validator(mode="after")
    def _arc(self) -> DCArcParams:
        if self.arc_start_deg == self.arc_end_deg:
            raise ValueError("arc_start_deg and arc_end_deg must differ")
        return self


class RotationArc(BaseModel):
    """Rotation from ``start_deg`` to ``end_deg`` at a fixed tilt."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    kind: Literal["rotation"] = "rotation"
    tilt_deg: Tilt
    start_deg: Rotation
    end_deg: Rotation

    @model_validator(mode="after")
    def _len(self) -> RotationArc:
        if self.start_deg == self.end_deg:
            raise ValueError("a rotation arc needs start_deg != end_deg")
        return self


class TiltArc(BaseModel):
    """Tilt from ``start_deg`` to ``end_deg`` at a fixed rotation."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    kind: Literal["tilt"] = "tilt"
    rotation_deg: Rotation
    start_deg: Tilt
    end_deg: Tilt

    @model_validator(mode="after")
    def _len(self) -> TiltArc:
        if self.start_deg == self.end_deg:
            raise ValueError("a tilt arc needs start_deg != end_deg")
        return self


Arc = Annotated[RotationArc | TiltArc, Field(discriminator="kind")]

# The multi-arc orbit of the paper's Experiment C (Artis Pheno): two identical 120 deg arcs at
# +10 deg tilt with the object turned ~90 deg between them (together 210 deg), a 120 deg arc at
# -20 deg tilt, and a tilting arc from -25 to +30 deg.
PRESETS: dict[str, list[dict[str, float | str]]] = {
    "pheno": [
        {"kind": "rotation", "tilt_deg": 10.0, "start_deg": 0.0, "end_deg": 120.0},
        {"kind": "rotation", "tilt_deg": 10.0, "start_deg": 90.0, "end_deg": 210.0},
        {"kind": "rotation", "tilt_deg": -20.0, "start_deg": 45.0, "end_deg": 165.0},
        {"kind": "tilt", "rotation_deg": 105.0, "start_deg": -25.0, "end_deg": 30.0},
    ]
}


class MultiArcParams(_Params):
    """Any list of arcs (rotation arcs at a fixed tilt, tilt arcs at a fixed rotation), or a preset."""

    n_frames: int = Field(857, ge=2, le=MAX_FRAMES, description="number of projection frames")
    preset: Literal["pheno"] | None = Field(None, description="named arc list; 'pheno' is the paper's Experiment C")
    arcs: list[Arc] | None = Field(None, min_length=1, max_length=64)

    @model_validator(mode="after")
    def _one_source(self) -> MultiArcParams:
        if (self.preset is None) == (self.arcs is None):
            raise ValueError("give exactly one of 'preset' (one of ['pheno']) or 'arcs'")
        if self.n_frames < 2 * len(self.resolved_arcs()):
            raise ValueError(f"n_frames must be at least 2 per arc ({2 * len(self.resolved_arcs())})")
        return self

    def resolved_arcs(self) -> list[RotationArc | TiltArc]:
        """The arcs, from the preset when one is named."""
        if self.arcs is not None:
            return list(self.arcs)
        out: list[RotationArc | TiltArc] = []
        for a in PRESETS[str(self.preset)]:
            out.append(RotationArc(**a) if a["kind"] == "rotation" else TiltArc(**a))
        return out


class WaypointsParams(_Params):
    """A polyline through ``(rotation_deg, tilt_deg)`` points, from a CSV/YAML file or given inline."""

    path: str | None = Field(None, description="CSV (columns rotation_deg,tilt_deg) or YAML file")
    points: list[tuple[Rotation, Tilt]] | None = Field(
        None, min_length=2, description="[[rotation_deg, tilt_deg], ...]"
    )

    @model_validator(mode="after")
    def _source(self) -> WaypointsParams:
        if self.path is None and self.points is None:
            raise ValueError("give 'path' (CSV or YAML of rotation_deg, tilt_deg) or 'points'")
        return self


ORBIT_KINDS: dict[str, type[_Params]] = {
    "circular": CircularParams,
    "sawtooth": SawtoothParams,
    "dcarc": DCArcParams,
    "multiarc": MultiArcParams,
    "waypoints": WaypointsParams,
}
