"""A connected bench: hexapod, rotation stage, X-ray generator and detector of one configuration.

``open_bench(config, sim=True)`` starts the twins in-process (``sim://bench``) so that
nothing else needs to run; otherwise it connects the configured URIs. The engine talks
to devices only through :class:`Bench`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from acquire.config import BenchConfig
from acquire.errors import AcquireError
from acquire.kinematics import HEXAPOD_AXES, HEXAPOD_UNITS
from devices.base import DeviceInfo, Status
from devices.errors import NotReferencedError, OutOfLimitsError
from devices.factory import open_device
from devices.factory import stop_all as stop_devices
from orbitct.scanfile.keys import ImageKey

log = logging.getLogger(__name__)
SIM_WORLD = "bench"
STAGE_AXIS = "R"
SIM_REPLY_TIMEOUT_S = 5.0
SIM_FRAME_TIMEOUT_S = 20.0


class Bench:
    """The four devices of a bench behind the calls the engine needs (units: deg and mm at this edge)."""

    def __init__(self, config: BenchConfig, hexapod: Any, stage: Any, xray: Any, detector: Any, *, sim: bool) -> None:
        self.config = config
        self.hexapod, self.stage, self.xray, self.detector = hexapod, stage, xray, detector
        self.sim = sim
        self.axes: dict[str, str] = {f"rotation_stage.{STAGE_AXIS}": "deg"}
        self.axes.update({f"hexapod.{a}": u for a, u in zip(HEXAPOD_AXES, HEXAPOD_UNITS)})
        self.phantom: Any = None
        self._background: dict[str, Status[Any]] = {}
        self._superseded: list[Status[Any]] = []
        self._last_truth: NDArray[np.float64] | None = None

    @property
    def devices(self) -> list[Any]:
        """Every device of the bench."""
        return [d for d in (self.hexapod, self.stage, self.xray, self.detector) if d is not None]

    async def describe(self) -> list[DeviceInfo]:
        """Model, serial, axes and limits of every device."""
        return list(await asyncio.gather(*(d.describe() for d in self.devices)))

    # ------------------------------------------------------------ set-up
    async def prepare(self, config: BenchConfig) -> None:
        """Reference and servo the axes if needed, set the pivot, velocities and X-ray technique; arm the detector."""
        for dev in (self.hexapod, self.stage):
            ref = await dev.referenced()
            if not all(ref.values()):
                if not self.sim:  # referencing moves the axes to their switches: an operator's decision
                    missing = ", ".join(a for a, ok in ref.items() if not ok)
                    raise NotReferencedError(
                        f"{dev.name}: axes {missing} are not referenced; reference them first "
                        f"(REST: POST /devices/{dev.name}/reference); a scan never references real axes on its own"
                    )
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

    async def _set_pivot(self, pivot_mm: Sequence[float], timeout_s: float) -> None:
        current = await self.hexapod.pivot()
        want = {"R": float(pivot_mm[0]), "S": float(pivot_mm[1]), "T": float(pivot_mm[2])}
        if all(abs(current[k] - want[k]) < 1e-6 for k in want):
            return
        await asyncio.wait_for(self.hexapod.move({"U": 0.0, "V": 0.0, "W": 0.0}), timeout_s)
        await self.hexapod.set_pivot(want["R"], want["S"], want["T"])

    async def device_limits(self) -> dict[str, tuple[float, float]]:
        """Controller soft limits keyed like the pre-flight axes (``rotation_stage``, ``hexapod.X``, ...)."""
        stage, hexa = await asyncio.gather(self.stage.limits(), self.hexapod.limits())
        out = {"rotation_stage": tuple(stage[STAGE_AXIS])}
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

    # ------------------------------------------------------------ motion
    async def move_to(self, stage_deg: float, hexapod: Mapping[str, float], timeout_s: float) -> None:
        """Move stage and hexapod at once and wait until both are on target."""
        moves = [self.stage.move({STAGE_AXIS: stage_deg}), self.hexapod.move(dict(hexapod))]
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
            raise AcquireError(f"move to stage {stage_deg:.3f} deg / hexapod {dict(hexapod)} not done within {timeout_s:g} s")
        for w in waits:
            exc = w.exception()
            if exc is not None:
                raise exc

    @property
    def motion_time_scale(self) -> float:
        """How many times faster than real the stage twin moves (1 for real hardware)."""
        return float(self.config.sim.time_scale) if self.sim else 1.0

    async def start_stage_sweep(self, target_deg: float, velocity_deg_s: float) -> None:
        """Set the stage velocity (wall-clock deg/s) and start a move to ``target_deg`` without waiting."""
        self._raise_background()
        await self.stage.set_velocity(velocity_deg_s / self.motion_time_scale)
        self._supersede("stage")
        self._background["stage"] = self.stage.move({STAGE_AXIS: target_deg})

    async def start_hexapod_move(self, hexapod: Mapping[str, float]) -> None:
        """Start a hexapod move without waiting (it may retarget one still running); failures surface at the next check."""
        self._raise_background()
        self._supersede("hexapod")
        self._background["hexapod"] = self.hexapod.move(dict(hexapod))

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

    async def stage_position_deg(self) -> float:
        """Stage read-back (deg)."""
        self._raise_background()
        return float((await self.stage.position())[STAGE_AXIS])

    async def read_positions(self) -> dict[str, float]:
        """Read-back of every axis as ``{'device.axis': value}``."""
        stage, hexa = await asyncio.gather(self.stage.position(), self.hexapod.position())
        out = {f"rotation_stage.{STAGE_AXIS}": float(stage[STAGE_AXIS])}
        out.update({f"hexapod.{a}": float(hexa[a]) for a in HEXAPOD_AXES})
        return out

    async def restore_stage_velocity(self) -> None:
        """Back to the configured stage velocity after a continuous sweep."""
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
    async def acquire(self, image_key: int, after_exposure: Callable[[], None] | None = None) -> tuple[NDArray[Any], int]:
        """One frame: dark (no X-rays), flat (open beam) or projection (X-ray exposure -> detector).

        ``after_exposure`` is called once the X-ray exposure is over, before the frame is read out.
        """
        self._last_truth = None
        if image_key == ImageKey.DARK:
            frame = (await self.detector.acquire_dark(1))[0]
        elif image_key == ImageKey.FLAT:
            frame = (await self.detector.acquire_flat(1))[0]
        else:
            await self.xray.expose()
            if after_exposure is not None:
                after_exposure()
            frame = await self.detector.read_frame()
            tv = frame.meta.get("truth_vectors") if self.sim else None
            self._last_truth = np.asarray(tv, dtype=float) if tv is not None else None
        return frame.data, int(frame.number)

    async def xray_off(self) -> None:
        """Switch X-rays off."""
        await self.xray.xray_off()

    def mark_interrupted(self) -> None:
        """After a cancelled exchange a reply may still be in flight: make the GCS links reconnect before the next one."""
        for dev in (self.hexapod, self.stage):
            client = getattr(dev, "_client", None) or getattr(dev, "client", None)
            if client is not None and hasattr(client, "_stale"):
                client._stale = True

    async def stop_all(self) -> None:
        """Halt every axis and switch X-rays off, all at once; never raises."""
        errors = await stop_devices([self.xray, self.hexapod, self.stage])
        for exc in errors:
            log.error("stop_all: %s", exc)
        await self._settle_background()

    # ------------------------------------------------------------- truth
    def true_pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """Not used: the simulated panel reports the true view with each frame."""
        return None

    def last_true_vector(self) -> NDArray[np.float64] | None:
        """The true view the simulated detector imaged for the last projection."""
        return self._last_truth

    def truth_extras(self) -> dict[str, Any]:
        """True marker centres and the phantom description (simulated benches only)."""
        if not self.sim or self.phantom is None:
            return {}
        return {"markers_xyz": np.asarray(self.phantom.markers_xyz), "phantom": self.phantom.to_json()}

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


def sim_options(config: BenchConfig) -> dict[str, dict[str, Any]]:
    """Twin options per device for an in-process simulated bench of ``config``."""
    det = config.geometry.detector
    # the twins share this machine's CPU with the scan: allow for a loaded machine in reply time-outs
    return {
        "hexapod": {"time_scale": config.sim.time_scale, "timeout_s": SIM_REPLY_TIMEOUT_S,
                    "stack_order": config.stack.order},
        "rotation_stage": {"time_scale": config.sim.time_scale, "timeout_s": SIM_REPLY_TIMEOUT_S},
        "xray": {"time_scale": config.sim.time_scale, "timeout_s": SIM_REPLY_TIMEOUT_S},
        "detector": {"rows": det.rows, "cols": det.cols, "sad_mm": config.geometry.sad_mm,
                     "sdd_mm": config.geometry.sdd_mm, "phantom": config.sim.phantom, "seed": config.sim.seed,
                     "timeout_s": SIM_FRAME_TIMEOUT_S},
    }


@contextlib.asynccontextmanager
async def open_bench(config: BenchConfig, *, sim: bool = False) -> AsyncIterator[Bench]:
    """Connect every device of ``config`` (in-process twins when ``sim``); stops and closes them on exit."""
    uris = config.devices.model_dump()
    opts: dict[str, dict[str, Any]] = {k: {} for k in uris}
    if sim:
        uris = {k: f"sim://{SIM_WORLD}" for k in uris}
        opts = sim_options(config)
    opened: dict[str, Any] = {}
    try:
        for kind in ("hexapod", "rotation_stage", "xray", "detector"):
            opened[kind] = await open_device(kind, kind, uris[kind], **opts[kind])
        bench = Bench(config, opened["hexapod"], opened["rotation_stage"], opened["xray"], opened["detector"], sim=sim)
        if sim:
            from orbitct.phantoms.experiments import experiment_phantom

            bench.phantom = experiment_phantom(config.sim.phantom, seed=config.sim.seed)
    except BaseException:
        for dev in opened.values():
            with contextlib.suppress(Exception):
                await dev.close()
        raise
    try:
        yield bench
    finally:
        await bench.close()
