"""Bench and C-arm configurations: pydantic models loaded from ``config/*.yaml``.

Degrees and milliseconds appear only here (``*_deg``, ``*_ms``); the rest of the
package works in radians, millimetres and seconds.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal, Self

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from acquire.errors import ConfigError
from devices.errors import UriError
from devices.uri import parse_uri
from orbitct.geometry import Panel, ViewGeometry
from orbitct.reference_bench import BB_DIAMETER_MM, SAD_MM, SDD_MM, reference_panel


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


Range = tuple[float, float]


def _check_range(name: str, r: Range) -> Range:
    if not (math.isfinite(r[0]) and math.isfinite(r[1]) and r[0] < r[1]):
        raise ValueError(f"{name} must be [low, high] with low < high, got {list(r)}")
    return r


def _check_uri(uri: str) -> str:
    try:
        parse_uri(uri)
    except UriError as exc:
        raise ValueError(str(exc)) from None
    return uri


class DetectorConfig(_Model):
    """Frame shape and pixel pitch; the pitch defaults to the reference panel read out at that size."""

    rows: int = Field(768, ge=8, le=8192)
    cols: int = Field(768, ge=8, le=8192)
    pitch_mm: tuple[float, float] | None = Field(None, description="[column pitch, row pitch] in mm")
    binning: int = Field(1, ge=1, le=8)

    @field_validator("pitch_mm")
    @classmethod
    def _positive(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not (v[0] > 0 and v[1] > 0):
            raise ValueError(f"pitches must be > 0 mm, got {list(v)}")
        return v

    def panel(self) -> Panel:
        """The pixel grid this configures."""
        if self.pitch_mm is not None:
            return Panel(self.rows, self.cols, *self.pitch_mm)
        return Panel(self.rows, self.cols, reference_panel(self.cols).pitch_col, reference_panel(self.rows).pitch_row)


class GeometryConfig(_Model):
    """Source and detector: SAD, SDD, detector, panel offsets and in-plane rotation."""

    sad_mm: float = Field(SAD_MM, gt=0)
    sdd_mm: float = Field(SDD_MM, gt=0)
    detector: DetectorConfig = DetectorConfig()
    du_mm: float = 0.0
    dv_mm: float = 0.0
    eta_deg: float = Field(0.0, ge=-10, le=10)

    @model_validator(mode="after")
    def _sdd_beyond_sad(self) -> GeometryConfig:
        if self.sdd_mm <= self.sad_mm:
            raise ValueError(
                f"sdd_mm ({self.sdd_mm}) must exceed sad_mm ({self.sad_mm}): the detector lies beyond the isocenter"
            )
        return self

    def lab_view(self) -> ViewGeometry:
        """The fixed source/detector at the reference view (theta = phi = 0), lab frame."""
        return ViewGeometry.from_carm(
            0.0,
            0.0,
            self.sad_mm,
            self.sdd_mm,
            self.detector.panel(),
            du=self.du_mm,
            dv=self.dv_mm,
            eta=math.radians(self.eta_deg),
        )

    def carm_views(self, theta_rad: Any, phi_rad: Any) -> ViewGeometry:
        """Nominal C-arm views for angles in radians."""
        return ViewGeometry.from_carm(
            theta_rad,
            phi_rad,
            self.sad_mm,
            self.sdd_mm,
            self.detector.panel(),
            du=self.du_mm,
            dv=self.dv_mm,
            eta=math.radians(self.eta_deg),
        )


class ExposureConfig(_Model):
    """X-ray technique and frame timing."""

    kv: float = Field(90.0, ge=20, le=150)
    ma: float = Field(1.0, gt=0, le=1000)
    exposure_ms: float = Field(10.0, gt=0, le=10000)
    frame_rate_hz: float = Field(30.0, gt=0, le=1000)
    prep_ms: float = Field(
        200.0,
        ge=0,
        le=60000,
        description="the generator's preparation time (PREP to READY); "
        "between exposures high voltage stays on only while the next one is due within it",
    )


class CalibrationFramesConfig(_Model):
    """How many darks and flats to take before and after the projections."""

    darks_before: int = Field(4, ge=0, le=1000)
    flats_before: int = Field(4, ge=0, le=1000)
    darks_after: int = Field(2, ge=0, le=1000)
    flats_after: int = Field(2, ge=0, le=1000)


class BenchDevices(_Model):
    """Device URIs of the bench (``sim://bench`` for in-process twins, ``tcp://host:port``, ``serial://...``)."""

    hexapod: str = "sim://bench"
    rotation_stage: str = "sim://bench"
    xray: str = "sim://bench"
    detector: str = "sim://bench"

    _uris = field_validator("hexapod", "rotation_stage", "xray", "detector")(classmethod(lambda cls, v: _check_uri(v)))

    @model_validator(mode="after")
    def _simulated_panel_sees_its_source(self) -> BenchDevices:
        panel = parse_uri(self.detector)
        if panel.scheme == "sim":  # a twin panel renders the exposures of its own world's X-ray twin, no other
            source = parse_uri(self.xray)
            if source.scheme != "sim" or source.host != panel.host:
                raise ValueError(
                    f"detector {self.detector} is a simulated panel: it takes frames only on exposures of "
                    f"the X-ray twin of its world (xray: sim://{panel.host}), not of xray {self.xray}; "
                    "make both sim:// or neither"
                )
        return self


class StackConfig(_Model):
    """How the rotation stage and hexapod are stacked, and the hexapod pivot point (lab, mm)."""

    order: Literal["stage_on_hexapod", "hexapod_on_stage"] = "stage_on_hexapod"
    pivot_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)


class HexapodLimits(_Model):
    """Soft limits per hexapod axis (checked in addition to the controller's coupled workspace)."""

    x_mm: Range = (-50.0, 50.0)
    y_mm: Range = (-50.0, 50.0)
    z_mm: Range = (-25.0, 25.0)
    u_deg: Range = (-30.0, 30.0)
    v_deg: Range = (-30.0, 30.0)
    w_deg: Range = (-30.0, 30.0)

    @model_validator(mode="after")
    def _ranges(self) -> HexapodLimits:
        for name in type(self).model_fields:
            _check_range(name, getattr(self, name))
        return self


class BenchLimits(_Model):
    """Soft limits of every bench axis, plus speeds the plan may ask for."""

    rotation_stage_deg: Range = (-370.0, 370.0)
    hexapod: HexapodLimits = HexapodLimits()
    stage_velocity_deg_s: float = Field(90.0, gt=0, le=720)
    hexapod_velocity_mm_s: float = Field(20.0, gt=0, le=200)

    @field_validator("rotation_stage_deg")
    @classmethod
    def _stage_range(cls, v: Range) -> Range:
        return _check_range("rotation_stage_deg", v)


class MotionConfig(_Model):
    """Step-and-shoot timing and time-outs."""

    settle_ms: float = Field(5.0, ge=0, le=10000)
    move_timeout_s: float = Field(30.0, gt=0, le=600)
    overlap_readout: bool = Field(
        False,
        description="step mode: start the next move once the exposure is over, "
        "while the panel reads out (a panel integrates only during the exposure)",
    )


class StallConfig(_Model):
    """Progress bounds per device, above the drivers' per-command time-outs: past one the scan stops, naming the device.

    The motion bound is ``motion.move_timeout_s`` (a move to the next frame on target).
    """

    frame_s: float = Field(
        5.0,
        gt=0,
        le=600,
        description="detector: a frame must arrive within this long after its "
        "exposure (darks and flats: after the trigger, plus the exposure time)",
    )
    exposure_s: float = Field(
        2.0,
        gt=0,
        le=600,
        description="generator: an exposure must be over within this long "
        "beyond its exposure time and the preparation time",
    )


class StorageConfig(_Model):
    """Disk space around a scan file: what must stay free on its filesystem."""

    reserve_mb: float = Field(
        200.0,
        ge=0,
        le=1e6,
        description="a scan that would leave less than this free is "
        "refused before anything moves; a running scan stops cleanly when less than half of it "
        "(plus two frames) is left",
    )


class SimConfig(_Model):
    """What the in-process twins image (``--sim``): phantom and BB size of experiment A."""

    phantom: str = Field("A", description="orbitct.phantoms experiment: A, B or C")
    bb_diameter_mm: float = Field(BB_DIAMETER_MM, gt=0, le=20)
    bbs_mm: list[tuple[float, float, float]] | None = Field(
        None,
        min_length=1,
        max_length=40,
        description="BB centres (object frame, mm) taped instead of the experiment's own, e.g. a plan's "
        "(orbitct scan --bbs-from PLAN); of bb_diameter_mm",
    )
    seed: int = 0
    time_scale: float = Field(1.0, ge=0.1, le=1000, description="twin motion and exposure run this many times faster")
    detector: Literal["clean", "realistic"] = Field(
        "clean",
        description="the simulated panel's images: clean, or realistic (wider blur, scatter, lag, dead pixels and "
        "columns; orbitct.simulator.DetectorModel.preset)",
    )
    clutter: Literal["none", "anatomy"] = Field(
        "none",
        description="anatomy: experiment C's torso with a patient's fat, vessels, ribs, a guide wire and ECG leads "
        "(orbitct.phantoms.anatomy; only for phantom C)",
    )
    beam: Literal["mono", "polychromatic"] = Field(
        "mono",
        description="the simulated tube's beam: mono (one energy), or polychromatic (a tungsten spectrum at the "
        "generator's kV through 3 mm Al and 0.1 mm Cu: beam hardening, and kV changes contrast; "
        "orbitct.simulator.Beam.preset)",
    )

    @model_validator(mode="after")
    def _clutter_on_c(self) -> Self:
        if self.clutter != "none" and self.phantom.upper() != "C":
            raise ValueError(f"clutter {self.clutter!r} is made for phantom C's torso, not phantom {self.phantom!r}")
        return self

    def detector_model(self) -> Any:
        """The simulated panel's detector model (:meth:`orbitct.simulator.DetectorModel.preset`)."""
        from orbitct.simulator import DetectorModel

        return DetectorModel.preset(self.detector)

    def beam_model(self) -> Any:
        """The simulated tube's beam (:meth:`orbitct.simulator.Beam.preset`; None: one energy)."""
        from orbitct.simulator import Beam

        return Beam.preset(self.beam)

    def imaged(self) -> Any:
        """What the twins image: the experiment's name, or its object (with ``clutter``, or with ``bbs_mm``'s
        BBs)."""
        if self.bbs_mm is None and self.clutter == "none":
            return self.phantom
        from orbitct.phantoms.experiments import experiment_phantom

        phantom = experiment_phantom(self.phantom, seed=self.seed, clutter=self.clutter)
        return phantom if self.bbs_mm is None else phantom.with_markers(self.bbs_mm, self.bb_diameter_mm)


class _RigConfig(_Model):
    """What every rig's configuration has: the source/detector geometry."""

    geometry: GeometryConfig = GeometryConfig()
    stall: StallConfig = StallConfig()
    storage: StorageConfig = StorageConfig()

    def with_detector_size(self, size: int | None) -> Self:
        """The same rig with a square detector of ``size`` pixels on the same panel (None: unchanged)."""
        if size is None:
            return self
        det = self.geometry.detector.model_copy(update={"rows": size, "cols": size, "pitch_mm": None})
        return self.model_copy(update={"geometry": self.geometry.model_copy(update={"detector": det})})


class BenchConfig(_RigConfig):
    """A test bench: fixed source/detector, object moved by a rotation stage and a hexapod."""

    kind: Literal["bench"] = "bench"
    name: str = "bench"
    devices: BenchDevices = BenchDevices()
    stack: StackConfig = StackConfig()
    geometry: GeometryConfig = GeometryConfig()
    limits: BenchLimits = BenchLimits()
    motion: MotionConfig = MotionConfig()
    exposure: ExposureConfig = ExposureConfig()
    calibration_frames: CalibrationFramesConfig = CalibrationFramesConfig()
    sim: SimConfig = SimConfig()

    def axis_limits(self) -> dict[str, Range]:
        """The configured soft limits keyed like ``/frames/commanded`` (deg, mm)."""
        hl = self.limits.hexapod
        out = {"rotation_stage.R": self.limits.rotation_stage_deg}
        out.update(
            {
                f"hexapod.{a}": getattr(hl, f"{a.lower()}_{u}")
                for a, u in (("X", "mm"), ("Y", "mm"), ("Z", "mm"), ("U", "deg"), ("V", "deg"), ("W", "deg"))
            }
        )
        return out


class CArmLimits(_Model):
    """Angle ranges and step limits of a robotic C-arm."""

    primary_deg: Range = (-185.0, 185.0)
    secondary_deg: Range = (-45.0, 45.0)
    max_step_deg: float = Field(5.0, gt=0, le=90)
    speed_deg_s: float = Field(30.0, gt=0, le=180)

    @model_validator(mode="after")
    def _ranges(self) -> CArmLimits:
        _check_range("primary_deg", self.primary_deg)
        _check_range("secondary_deg", self.secondary_deg)
        return self


class CArmDevices(_Model):
    """Device URIs of a C-arm (navigation-point controller and its frame source)."""

    carm: str = "sim://carm"

    _uris = field_validator("carm")(classmethod(lambda cls, v: _check_uri(v)))


class CArmConfig(_RigConfig):
    """A robotic C-arm driven through navigation points."""

    kind: Literal["carm"] = "carm"
    name: str = "carm"
    devices: CArmDevices = CArmDevices()
    geometry: GeometryConfig = GeometryConfig()
    limits: CArmLimits = CArmLimits()
    motion: MotionConfig = MotionConfig(settle_ms=0.0, move_timeout_s=120.0)
    exposure: ExposureConfig = ExposureConfig()
    calibration_frames: CalibrationFramesConfig = CalibrationFramesConfig()
    sim: SimConfig = SimConfig(phantom="C")


AnyConfig = Annotated[BenchConfig | CArmConfig, Field(discriminator="kind")]
_ADAPTER: TypeAdapter[BenchConfig | CArmConfig] = TypeAdapter(AnyConfig)


def _describe(exc: ValidationError, source: str) -> str:
    lines = []
    for err in exc.errors():
        parts = [str(p) for p in err["loc"]]
        if parts and parts[0] in ("bench", "carm"):
            parts = parts[1:]  # the discriminator tag, not a field
        loc = ".".join(parts) or "(top level)"
        msg = err["msg"].removeprefix("Value error, ")
        lines.append(f"{loc}: {msg}")
    return f"{source}: invalid configuration: " + "; ".join(lines)


def parse_config(data: Any, source: str = "configuration") -> BenchConfig | CArmConfig:
    """Validate a mapping into a bench or C-arm configuration; :class:`ConfigError` names field and reason."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    data = dict(data)
    data.setdefault("kind", "bench")
    try:
        return _ADAPTER.validate_python(data)
    except ValidationError as exc:
        raise ConfigError(_describe(exc, source)) from None


def load_config(path: str | Path) -> BenchConfig | CArmConfig:
    """Read and validate ``config/*.yaml``."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: no such configuration file")
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({exc})") from None
    return parse_config(data, str(p))
