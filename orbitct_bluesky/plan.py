"""A bluesky plan for an orbitct orbit on the bench: pre-flight, then move, expose and read frame by frame.

The plan is built from the same :class:`~acquire.options.ScanOptions` and bench configuration as ``orbitct scan``
(step mode), so it takes the same frames: darks and flats before and after, each projection moved to, settled,
exposed and read with its encoder read-backs. Nothing moves before orbitct's pre-flight has checked every frame
against the configured and the controllers' limits and the hexapod's workspace. A stop, pause, abort or halt from
the RunEngine halts every axis and switches X-rays off: the RunEngine stops every device the run set (the axes
moved, the generator's technique set) and pauses the generator; a paused run goes on from the frame it was on.
"""

from __future__ import annotations

import time
from collections.abc import Awaitable, Callable, Generator, Mapping
from dataclasses import dataclass
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
import numpy as np
from bluesky.protocols import Readable
from bluesky.utils import Msg

from acquire.config import BenchConfig
from acquire.errors import AcquireError
from acquire.kinematics import STAGE_AXIS
from acquire.options import ScanOptions
from acquire.plan import ScanPlan
from acquire.rigs.bench import BenchRig, bench_links
from acquire.runner import ScanRequest, build_plan
from orbitct.scanfile import ImageKey
from orbitct_bluesky.devices import HEXAPOD_AXES, FlatPanel, Hexapod, RotationStage, XrayGenerator
from orbitct_bluesky.scanfile_callback import orbitct_metadata

#: the stream the plan's frames go to (:class:`~orbitct_bluesky.ScanFileCallback` reads it by default)
STREAM = "primary"


@dataclass(frozen=True)
class Bench:
    """The four ophyd-async devices of one bench and its orbitct configuration."""

    config: BenchConfig
    hexapod: Hexapod
    stage: RotationStage
    xray: XrayGenerator
    panel: FlatPanel

    @classmethod
    def from_config(cls, config: BenchConfig, *, sim: bool = False) -> Bench:
        """The bench's devices at the configuration's URIs with orbitct's driver options (``sim``: its twins, on
        loopback sockets, as ``orbitct scan --sim`` runs them). Connect them before use."""
        links = bench_links(config, sim=sim)
        return cls(
            config,
            Hexapod(links["hexapod"].uri, "hexapod", **links["hexapod"].options),
            RotationStage(links["rotation_stage"].uri, "stage", **links["rotation_stage"].options),
            XrayGenerator(links["xray"].uri, "xray", **links["xray"].options),
            FlatPanel(links["detector"].uri, "panel", **links["detector"].options),
        )

    @property
    def devices(self) -> tuple[Hexapod, RotationStage, XrayGenerator, FlatPanel]:
        """Every device of the bench."""
        return (self.hexapod, self.stage, self.xray, self.panel)

    @property
    def simulated(self) -> bool:
        """Whether every device is orbitct's twin."""
        return all(d.simulated for d in self.devices)

    def rig(self) -> BenchRig:
        """orbitct's bench over the same drivers: its pre-flight and set-up run unchanged."""
        return BenchRig(
            self.config,
            self.hexapod.driver,
            self.stage.driver,
            self.xray.driver,
            self.panel.driver,
            sim=self.simulated,
        )

    def axes(self) -> dict[str, tuple[str, str, str]]:
        """Every recorded axis (as orbitct names it) with its unit and its read-back and setpoint data keys."""
        out = {STAGE_AXIS: ("deg", f"{self.stage.name}-R", f"{self.stage.name}-R_setpoint")}
        for axis, unit in zip(HEXAPOD_AXES, self.hexapod.units, strict=True):
            out[f"hexapod.{axis}"] = (unit, f"{self.hexapod.name}-{axis}", f"{self.hexapod.name}-{axis}_setpoint")
        return out


def plan_frames(bench: Bench, options: ScanOptions | None = None) -> ScanPlan:
    """The frames ``orbitct scan`` takes of ``options`` on the bench (step mode; :class:`AcquireError` naming what
    is wrong)."""
    options = options if options is not None else ScanOptions()
    if options.mode != "step":
        raise AcquireError(
            "the bluesky orbit plan moves, settles and exposes frame by frame (step mode); continuous mode runs "
            "with orbitct scan or the service"
        )
    fields = options.model_dump(exclude={"frame_rate_hz"})
    return build_plan(ScanRequest(config=bench.config, out="", **fields), bench.config)


def orbit_plan(
    bench: Bench, options: ScanOptions | None = None, *, md: Mapping[str, Any] | None = None
) -> Generator[Msg, Any, None]:
    """Scan ``options``'s orbit on ``bench`` (connected devices): one run of start, one ``primary`` stream with an
    event per frame (frame, image key, nominal view, read-backs and setpoints of every axis), stop.

    Before anything moves: the frames are planned and checked (pre-flight); a frame the bench cannot take ends
    the plan with :class:`AcquireError` saying which and why. ``md``: more start-document metadata."""
    frames = plan_frames(bench, options)
    rig = bench.rig()
    config = bench.config
    yield from _call(lambda: rig.preflight(frames, "step", config.exposure.frame_rate_hz))
    yield from _call(lambda: rig.prepare(frames))
    entry = orbitct_metadata(
        frames.panel,
        bench.axes(),
        orbit_name=frames.orbit_name,
        orbit_params=dict(frames.orbit_params),
        marker_diameter_mm=config.sim.bb_diameter_mm if bench.simulated else None,
        keys={
            "image": f"{bench.panel.name}-image",
            "image_key": f"{bench.panel.name}-image_key",
            "nominal_vector": "nominal_vector",
            "true_vector": f"{bench.panel.name}-true_vector" if bench.simulated else None,
        },
        frames=(frames.image_key.tolist(), frames.nominal.vectors.tolist()),
    )
    start = {
        "plan_name": "orbit_plan",
        "num_points": frames.n_frames,
        "detectors": [bench.panel.name],
        "motors": [bench.stage.name, bench.hexapod.name],
        "orbitct": entry,
        **dict(md or {}),
    }
    nominal = _NominalView()
    readers: list[Readable[Any]] = [bench.panel, bench.stage, bench.hexapod, bench.xray, nominal]

    ex = config.exposure
    technique = {"kv": ex.kv, "ma": ex.ma, "exposure_ms": ex.exposure_ms}

    @bpp.run_decorator(md=start)  # type: ignore[untyped-decorator]
    def frames_plan() -> Generator[Msg, Any, None]:
        # set in the run: however it ends (a stop, pause, abort or halt too), the RunEngine stops the generator
        yield from bps.mv(bench.xray, technique)
        for f in frames:
            yield from bps.checkpoint()  # a paused run goes on from this frame
            moves: list[Any] = [bench.stage, {"R": f.targets[STAGE_AXIS]}]
            moves += [bench.hexapod, {a: f.targets[f"hexapod.{a}"] for a in HEXAPOD_AXES}]
            yield from bps.mv(*moves)
            yield from bps.sleep(config.motion.settle_ms / 1000.0)
            yield from bps.mv(bench.panel.image_key, int(f.image_key))
            if f.image_key == ImageKey.PROJECTION:
                yield from bps.trigger(bench.xray, wait=True)
            yield from bps.trigger(bench.panel, wait=True)
            nominal.vector = np.asarray(f.nominal_vector, dtype=np.float64).reshape(12)
            yield from bps.create(STREAM)  # read, not triggered again: a trigger would take another frame
            for reader in readers:
                yield from bps.read(reader)
            yield from bps.save()

    yield from frames_plan()


def _call(factory: Callable[[], Awaitable[Any]]) -> Generator[Msg, Any, Any]:
    """Run a coroutine in the RunEngine's loop and return its result (its exception raised in the plan)."""
    (done,) = yield from bps.wait_for([factory])
    return done.result()


class _NominalView:
    """The nominal view of the frame being read, as a readable the stream records (``nominal_vector``)."""

    name = "orbit"
    parent = None

    def __init__(self) -> None:
        self.vector = np.full(12, np.nan)

    def describe(self) -> dict[str, Any]:
        return {"nominal_vector": {"source": "orbitct:plan", "dtype": "array", "shape": [12], "dtype_numpy": "<f8"}}

    def read(self) -> dict[str, Any]:
        return {"nominal_vector": {"value": self.vector.copy(), "timestamp": time.time()}}

    def read_configuration(self) -> dict[str, Any]:
        return {}

    def describe_configuration(self) -> dict[str, Any]:
        return {}
