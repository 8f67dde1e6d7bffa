"""The bench rig: a rotation stage on a hexapod moves the object between a fixed source and panel.

``open_bench(config, sim=True)`` starts the twins in-process (``sim://bench``) so that nothing else
needs to run; otherwise it connects the configured URIs. The engine talks to the devices only
through :class:`BenchRig` (a :class:`~acquire.rig.SweepRig`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from typing import Any, Protocol

from acquire.config import BenchConfig
from acquire.errors import NotReadyError, RefusedError, StallError
from acquire.kinematics import HEXAPOD_AXES, STAGE_AXIS
from acquire.plan import ScanPlan
from acquire.preflight import bench_preflight
from acquire.rigs.links import DeviceLink, configured_link
from acquire.stall import within
from devices.base import DeviceInfo, FrameSource, Referencing, Status, XraySource
from devices.errors import NotReferencedError, OutOfLimitsError
from devices.factory import open_device
from devices.factory import stop_all as stop_devices
from devices.frame_protocol import Frame
from orbitct.scanfile.keys import ImageKey

log = logging.getLogger(__name__)
SIM_WORLD = "bench"
STAGE = STAGE_AXIS.split(".")[1]  # the stage driver's axis name
SIM_REPLY_TIMEOUT_S = 5.0
SIM_FRAME_TIMEOUT_S = 20.0


BENCH_KINDS = ("hexapod", "rotation_stage", "xray", "detector")


class Hexapod(Referencing, Protocol):
    """What the bench needs of its hexapod beyond referenced axes: the pivot and the coupled workspace."""

    async def pivot(self) -> dict[str, float]:
        """Pivot point R, S, T (mm)."""

    async def set_pivot(self, r_mm: float, s_mm: float, t_mm: float) -> None:
        """Set the pivot point (only while U, V, W are 0)."""

    async def check_pose(
        self, targets: Mapping[str, float], current: Mapping[str, float] | None = None
    ) -> dict[str, float]:
        """Refuse a pose outside the soft limits or the coupled workspace (``OutOfLimitsError``)."""


def _device_axes(targets: Mapping[str, float], device: str) -> dict[str, float]:
    """``{'hexapod.X': 1.0, ...}`` -> ``{'X': 1.0, ...}`` for one device."""
    prefix = device + "."
    return {k[len(prefix) :]: float(v) for k, v in targets.items() if k.startswith(prefix)}


class BenchRig:
    """The four devices of a bench behind the calls the engine needs (units: deg and mm at this edge)."""

    sweep_axis = STAGE_AXIS

    def __init__(
        self,
        config: BenchConfig,
        hexapod: Hexapod,
        stage: Referencing,
        xray: XraySource,
        detector: FrameSource,
        *,
        sim: bool,
    ) -> None:
        self.config = config
        self.hexapod, self.stage, self.xray, self.detector = hexapod, stage, xray, detector
        self.sim = sim
        self.axes: dict[str, str] = {STAGE_AXIS: "deg"}
        self.axes.update({f"hexapod.{a}": u for a, u in zip(HEXAPOD_AXES, ("mm", "mm", "mm", "deg", "deg", "deg"))})
        self._background: dict[str, Status[Any]] = {}
        self._superseded: list[Status[Any]] = []
        # high voltage: the generator's preparation time (wall clock) and the last gap between two exposures
        self.prep_s = config.exposure.prep_ms / 1000.0 / self.motion_time_scale
        self._gap_s: float | None = None
        self._last_exposure: float | None = None

    @property
    def devices(self) -> list[Any]:
        """Every device of the bench."""
        return [self.hexapod, self.stage, self.xray, self.detector]

    async def describe(self) -> list[DeviceInfo]:
        """Model, serial, axes and limits of every device."""
        return list(await asyncio.gather(*(d.describe() for d in self.devices)))

    # ------------------------------------------------------------ checks
    async def device_limits(self) -> dict[str, tuple[float, float]]:
        """Controller soft limits keyed like the plan's axes (``rotation_stage.R``, ``hexapod.X``, ...)."""
        stage, hexa = await asyncio.gather(self.stage.limits(), self.hexapod.limits())
        out = {STAGE_AXIS: tuple(stage[STAGE])}
        out.update({f"hexapod.{a}": tuple(v) for a, v in hexa.items() if a in HEXAPOD_AXES})
        return out  # type: ignore[return-value]

    async def check_workspace(self, poses: Sequence[Mapping[str, float]]) -> int | None:
        """Index of the first pose the hexapod controller refuses (VMO?), or None."""
        for i, pose in enumerate(poses):
            try:
                await self.hexapod.check_pose(dict(pose))
            except OutOfLimitsError:
                return i
        return None

    async def preflight(self, plan: ScanPlan, mode: str, frame_rate_hz: float) -> None:
        """The generator able to expose (no fault, door closed); real axes referenced (a scan never references
        them); the panel's frames the size the plan records; every frame against the configured and the
        controllers' limits and the hexapod's workspace."""
        await self.xray.check_ready()
        if not self.sim:
            for dev in (self.hexapod, self.stage):
                unreferenced = await self._unreferenced(dev)
                if unreferenced:
                    raise NotReadyError(f"{unreferenced}; nothing moved")
        panel = (await self.detector.describe()).extra
        want = (plan.panel.rows, plan.panel.cols)
        if panel.get("rows") and panel.get("cols") and (panel["rows"], panel["cols"]) != want:
            raise RefusedError(
                f"{self.detector.name} delivers {panel['rows']} x {panel['cols']} px frames, the plan records "
                f"{want[0]} x {want[1]} (geometry.detector rows and cols of the configuration, or "
                "--detector-size); nothing moved"
            )
        await bench_preflight(
            plan,
            self.config,
            device_limits=await self.device_limits(),
            workspace_check=self.check_workspace,
            mode=mode,
            frame_rate_hz=frame_rate_hz,
        )

    # ------------------------------------------------------------ set-up
    async def prepare(self, plan: ScanPlan) -> None:
        """Reference and servo the axes if needed, set the pivot, velocities and X-ray technique; arm the detector."""
        config = self.config
        for dev in (self.hexapod, self.stage):
            unreferenced = await self._unreferenced(dev)
            if unreferenced:
                if not self.sim:  # referencing moves the axes to their switches: an operator's decision
                    raise NotReferencedError(unreferenced)
                await dev.reference()
            servo = await dev.servo_on()
            if not all(servo.values()):
                await dev.servo(True)
        await self._set_pivot(config.stack.pivot_mm, config.motion.move_timeout_s)
        await self.stage.set_velocity(config.limits.stage_velocity_deg_s)
        await self.hexapod.set_velocity(config.limits.hexapod_velocity_mm_s)
        ex = config.exposure
        await self.xray.configure(kv=ex.kv, ma=ex.ma, exposure_ms=ex.exposure_ms)
        await self.detector.set_trigger("xray")
        await self.detector.arm()

    @staticmethod
    async def _unreferenced(dev: Any) -> str:
        """Why ``dev`` cannot move yet: its axes that are not referenced, and how to reference them ('' if all are)."""
        missing = ", ".join(a for a, ok in (await dev.referenced()).items() if not ok)
        if not missing:
            return ""
        return (
            f"{dev.name}: axes {missing} are not referenced; reference them first (orbitct reference {dev.name} "
            f"--config CONFIG, or POST /devices/{dev.name}/reference over REST); a scan never references real axes "
            "on its own"
        )

    async def _set_pivot(self, pivot_mm: Sequence[float], timeout_s: float) -> None:
        current = await self.hexapod.pivot()
        want = {"R": float(pivot_mm[0]), "S": float(pivot_mm[1]), "T": float(pivot_mm[2])}
        if all(abs(current[k] - want[k]) < 1e-6 for k in want):
            return
        await asyncio.wait_for(self.hexapod.move({"U": 0.0, "V": 0.0, "W": 0.0}), timeout_s)
        await self.hexapod.set_pivot(want["R"], want["S"], want["T"])

    # ------------------------------------------------------------ motion
    async def move_to(self, targets: Mapping[str, float], timeout_s: float) -> None:
        """Move stage and hexapod at once and wait until both are on target (retargeting a sweep or a follow-up move
        still running from continuous mode: its own ending is expected)."""
        self._raise_background()
        self._supersede("stage")
        self._supersede("hexapod")
        moves = [
            self.stage.move(_device_axes(targets, "rotation_stage")),
            self.hexapod.move(_device_axes(targets, "hexapod")),
        ]
        waits = [asyncio.ensure_future(_await(m)) for m in moves]
        for w in waits:
            w.add_done_callback(_retrieve)  # outcomes are read even if this call is cancelled
        try:
            _, pending = await asyncio.wait(waits, timeout=timeout_s)
        except asyncio.CancelledError:  # cancelled from outside (Ctrl-C): the moves end with us (drivers halt)
            for m in moves:
                m.cancel()
            await asyncio.wait(waits, timeout=2.0)
            raise
        if pending:
            late = " and ".join(dev.name for dev, w in zip((self.stage, self.hexapod), waits) if w in pending)
            where = ", ".join(f"{k} {v:.3f}" for k, v in targets.items())
            raise StallError(late, f"did not reach {where}", timeout_s, "motion.move_timeout_s")
        for w in waits:
            exc = w.exception()
            if exc is not None:
                raise exc

    def travel_s(self, start: Mapping[str, float], end: Mapping[str, float]) -> float:
        """Stage and hexapod move at once, the hexapod's axes along a straight line (all arrive together)."""
        limits = self.config.limits
        stage = abs(end[STAGE_AXIS] - start[STAGE_AXIS]) / limits.stage_velocity_deg_s
        hexapod = max(
            (abs(end[k] - start[k]) for k in end if k.startswith("hexapod.")),
            default=0.0,
        )
        return max(stage, hexapod / limits.hexapod_velocity_mm_s) / self.motion_time_scale

    @property
    def motion_time_scale(self) -> float:
        """How many times faster than real the stage twin moves (1 for real hardware)."""
        return float(self.config.sim.time_scale) if self.sim else 1.0

    async def start_sweep(self, target: float, velocity: float) -> None:
        """Set the stage velocity (wall-clock deg/s) and start a move to ``target`` without waiting."""
        self._raise_background()
        await self.stage.set_velocity(velocity / self.motion_time_scale)
        self._supersede("stage")
        self._background["stage"] = self.stage.move({STAGE: target})

    async def start_move(self, targets: Mapping[str, float]) -> None:
        """Start a hexapod move without waiting (it may retarget one still running); failures surface at the next check."""
        self._raise_background()
        self._supersede("hexapod")
        self._background["hexapod"] = self.hexapod.move(_device_axes(targets, "hexapod"))

    def _supersede(self, kind: str) -> None:
        old = self._background.pop(kind, None)
        if old is not None:
            self._superseded.append(old)  # retargeted: its own ending (code 10) is expected, not an error

    def _raise_background(self) -> None:
        for kind, st in list(self._background.items()):
            if st.done:
                del self._background[kind]
                exc = st.exception()
                if exc is not None:
                    raise exc

    async def sweep_position(self) -> float:
        """Stage read-back (deg)."""
        self._raise_background()
        return float((await self.stage.position())[STAGE])

    async def read_positions(self) -> dict[str, float]:
        """Read-back of every axis as ``{'device.axis': value}``."""
        stage, hexa = await asyncio.gather(self.stage.position(), self.hexapod.position())
        out = {STAGE_AXIS: float(stage[STAGE])}
        out.update({f"hexapod.{a}": float(hexa[a]) for a in HEXAPOD_AXES})
        return out

    async def restore(self) -> None:
        """X-rays off; background moves settled; the configured stage velocity back (after a continuous sweep)."""
        await self.xray.xray_off()
        await self._settle_background()
        await self.stage.set_velocity(self.config.limits.stage_velocity_deg_s)

    async def _settle_background(self) -> None:
        pending = list(self._background.values()) + self._superseded
        self._background, self._superseded = {}, []
        for st in pending:
            if not st.done:
                with contextlib.suppress(BaseException):
                    await asyncio.wait_for(asyncio.shield(asyncio.ensure_future(_await(st))), 0.5)
            if st.done and not st._task.cancelled():
                st.exception()  # retrieved: no "exception never retrieved" warnings

    # --------------------------------------------------------- exposures
    async def acquire(
        self, image_key: int, after_exposure: Callable[[], None] | None = None, *, next_exposure_s: float | None = None
    ) -> Frame:
        """One frame: dark (no X-rays), flat (open beam) or projection (X-ray exposure -> detector).

        ``after_exposure`` is called once the X-ray exposure is over, before the frame is read out.
        ``next_exposure_s``: how soon the next exposure is due (a sweep knows); None: as soon as this one came.
        """
        stall, ex = self.config.stall, self.config.exposure
        det = self.detector.name
        if image_key in (ImageKey.DARK, ImageKey.FLAT):
            take = self.detector.acquire_dark if image_key == ImageKey.DARK else self.detector.acquire_flat
            bound = stall.frame_s + ex.exposure_ms / 1000.0
            what = f"delivered no {'dark' if image_key == ImageKey.DARK else 'flat'} frame"
            return (await within(bound, det, what, "stall.frame_s", take(1)))[0]
        t0 = time.monotonic()
        if self._last_exposure is not None:
            self._gap_s = t0 - self._last_exposure
        # the next exposure further away than a preparation takes: high voltage goes off at once (and the next
        # exposure prepares again); nearer, it stays on. Unless the caller knows, the next one is taken to be as far
        # away as this one was from the last. (Where a preparation itself makes that gap longer than one, the
        # guess kept the generator off between all the exposures of a sweep after its run-up: each came a
        # preparation late, the sweep ran ahead of them, and a DCArc's second turn was exposed up to 210 degrees
        # from its angles.)
        if next_exposure_s is not None:
            release = next_exposure_s > self.prep_s
        else:
            release = self._gap_s is not None and self._gap_s > self.prep_s
        bound = stall.exposure_s + (ex.exposure_ms + ex.prep_ms) / 1000.0
        await within(
            bound, self.xray.name, "did not finish the exposure", "stall.exposure_s", self.xray.expose(release=release)
        )
        self._last_exposure = time.monotonic()
        if after_exposure is not None:
            after_exposure()
        return await within(
            stall.frame_s, det, "delivered no frame after the exposure", "stall.frame_s", self.detector.read_frame()
        )

    def last_exposure_s(self) -> tuple[float, float] | None:
        """When the generator's last exposure began and ended (``time.monotonic()``); None while unknown."""
        return self.xray.last_exposure_s

    async def prepare_exposure(self) -> None:
        """High voltage up while the axes move to the next projection, so the preparation overlaps the move;
        if the exposure comes later than the preparation time after READY, the generator's hold drops it again."""
        stall, ex = self.config.stall, self.config.exposure
        bound = stall.exposure_s + ex.prep_ms / 1000.0
        await within(
            bound, self.xray.name, "did not get ready for the exposure", "stall.exposure_s", self.xray.prepare()
        )

    def _resynchronise(self) -> None:
        """After a cancelled exchange a reply may still be in flight: the GCS links reconnect before the next one."""
        for dev in (self.hexapod, self.stage):
            client = getattr(dev, "_client", None)
            if client is not None and hasattr(client, "_stale"):
                client._stale = True

    async def stop_all(self, *, interrupted: bool = False) -> None:
        """Halt every axis and switch X-rays off, all at once; never raises."""
        if interrupted:
            self._resynchronise()
        errors = await stop_devices([self.xray, self.hexapod, self.stage])
        for exc in errors:
            log.error("stop_all: %s", exc)
        await self._settle_background()

    async def close(self) -> None:
        """Stop everything, then disconnect every device."""
        await self.stop_all()
        for dev in self.devices:
            with contextlib.suppress(Exception):
                await dev.close()


async def _await(st: Status[Any]) -> Any:
    return await st


def _retrieve(fut: asyncio.Future[Any]) -> None:
    if not fut.cancelled():
        fut.exception()


def device_options(config: BenchConfig) -> dict[str, dict[str, Any]]:
    """Driver options per device of a real bench: high voltage off once the next exposure is further away than
    the generator's preparation time."""
    return {"hexapod": {}, "rotation_stage": {}, "xray": {"hold_s": config.exposure.prep_ms / 1000.0}, "detector": {}}


def sim_options(config: BenchConfig) -> dict[str, dict[str, Any]]:
    """Twin and driver options per device for an in-process simulated bench of ``config``."""
    det = config.geometry.detector
    scale = config.sim.time_scale
    prep_s = config.exposure.prep_ms / 1000.0
    # the twins share this machine's CPU with the scan: allow for a loaded machine in reply time-outs
    return {
        "hexapod": {"time_scale": scale, "timeout_s": SIM_REPLY_TIMEOUT_S, "stack_order": config.stack.order},
        "rotation_stage": {"time_scale": scale, "timeout_s": SIM_REPLY_TIMEOUT_S},
        "xray": {"time_scale": scale, "prep_s": prep_s, "hold_s": prep_s / scale, "timeout_s": SIM_REPLY_TIMEOUT_S},
        "detector": {
            "rows": det.rows,
            "cols": det.cols,
            "sad_mm": config.geometry.sad_mm,
            "sdd_mm": config.geometry.sdd_mm,
            "phantom": config.sim.imaged(),
            "seed": config.sim.seed,
            "detector_model": config.sim.detector_model(),
            "beam": config.sim.beam_model(),
            "timeout_s": SIM_FRAME_TIMEOUT_S,
        },
    }


@contextlib.asynccontextmanager
async def open_bench(
    config: BenchConfig, *, sim: bool = False, links: Mapping[str, DeviceLink] | None = None
) -> AsyncIterator[BenchRig]:
    """Connect every device of ``config`` (in-process twins when ``sim``); stops and closes them on exit.

    ``links`` overrides where each device is reached (twins already running elsewhere, with ``sim``).
    """
    if links is None:
        links = bench_links(config, sim=sim)
    real_axes = [k for k in ("hexapod", "rotation_stage") if not links[k].uri.startswith("sim://")]
    if links["detector"].uri.startswith("sim://") and real_axes:
        log.warning(
            "the panel is simulated (%s) but %s not: its frames show the simulated object, unmoved by the "
            "real axes; a rehearsal of the motion, not a scan to calibrate or reconstruct",
            links["detector"].uri,
            " and ".join(real_axes) + (" are" if len(real_axes) > 1 else " is"),
        )
    opened: dict[str, Any] = {}
    try:
        for kind in BENCH_KINDS:
            opened[kind] = await open_device(kind, kind, links[kind].uri, **links[kind].options)
    except BaseException:
        for dev in opened.values():
            with contextlib.suppress(Exception):
                await dev.close()
        raise
    rig = BenchRig(config, opened["hexapod"], opened["rotation_stage"], opened["xray"], opened["detector"], sim=sim)
    try:
        yield rig
    finally:
        await rig.close()


def bench_links(config: BenchConfig, *, sim: bool) -> dict[str, DeviceLink]:
    """Where each bench device is reached: its configured URI, or ``sim://bench`` with twin and driver options."""
    if sim:
        return {kind: DeviceLink(f"sim://{SIM_WORLD}", opts) for kind, opts in sim_options(config).items()}
    uris, twins = config.devices.model_dump(), sim_options(config)
    # a sim:// twin in a real bench's configuration: the configuration's panel, distances, phantom, preparation
    # time and stack, at real speed (its time scale and the in-process reply time-outs are --sim's)
    twin_keys = {"rows", "cols", "sad_mm", "sdd_mm", "phantom", "seed", "prep_s", "stack_order"}
    return {
        kind: configured_link(uris[kind], opts, {k: v for k, v in twins[kind].items() if k in twin_keys})
        for kind, opts in device_options(config).items()
    }
