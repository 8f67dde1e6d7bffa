"""The C-arm rig: source and detector move around a fixed object through navigation points.

The orbit is exported as a navigation-point program (checked against the arm's ranges and
largest step), loaded at ``prepare``, and played point by point: a move to a frame's targets
visits the bridge points between orbit segments first. The C-arm carries source and detector;
its own systematic errors (tilt sag, isocenter drift, panel rotation) are what calibration has
to find, so no error is injected here.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator, Callable, Mapping
from typing import Any

from acquire.config import CArmConfig
from acquire.errors import AcquireError, PreflightError
from acquire.plan import CARM_AXES, ScanPlan
from acquire.rigs.links import DeviceLink, configured_link
from acquire.stall import within
from devices.carm import CArm
from devices.carm_program import CArmLimits, InfeasibleOrbitError, NavProgram, export_program
from devices.factory import open_device
from devices.factory import stop_all as stop_devices
from devices.frame_protocol import Frame
from orbitct.orbits import Orbit, make_orbit
from orbitct.scanfile.keys import ImageKey

log = logging.getLogger(__name__)
SIM_WORLD = "carm"
ANGLE_TOL_DEG = 1e-6


def carm_limits(cfg: CArmConfig) -> CArmLimits:
    """The exporter's limits from a C-arm configuration."""
    lim = cfg.limits
    return CArmLimits(
        primary_deg=(lim.primary_deg[0], lim.primary_deg[1]),
        secondary_deg=(lim.secondary_deg[0], lim.secondary_deg[1]),
        max_step_deg=lim.max_step_deg,
        max_speed_deg_s=lim.speed_deg_s,
    )


def export_orbit(orbit: Orbit, cfg: CArmConfig) -> NavProgram:
    """Navigation points for ``orbit``; an infeasible orbit raises :class:`PreflightError` naming the first bad frame."""
    try:
        return export_program(orbit, carm_limits(cfg), speed_deg_s=cfg.limits.speed_deg_s)
    except InfeasibleOrbitError as exc:
        raise PreflightError(exc.index, "carm", None, f"the C-arm's limits ({exc})") from None


class CArmRig:
    """A connected C-arm behind the calls the engine needs (step by step only)."""

    def __init__(self, config: CArmConfig, carm: CArm, *, sim: bool) -> None:
        self.config = config
        self.carm = carm
        self.sim = sim
        self.axes = dict(CARM_AXES)
        self.program: NavProgram | None = None
        self._point = -1  # last program point visited
        self._stops = 0  # counts stop_all calls: a move in progress visits no further point after one

    @property
    def devices(self) -> list[Any]:
        """The C-arm (it carries source and panel)."""
        return [self.carm]

    async def describe(self) -> list[Any]:
        """Model, serial, axes and limits of the C-arm."""
        return [await self.carm.describe()]

    def program_for(self, plan: ScanPlan) -> NavProgram:
        """The navigation program of a plan's orbit."""
        return export_orbit(make_orbit(plan.orbit_name, **dict(plan.orbit_params)), self.config)

    async def preflight(self, plan: ScanPlan, mode: str, frame_rate_hz: float) -> None:
        """The program (orbit limits, largest step) and every point against the connected arm's ranges."""
        if mode != "step":
            raise AcquireError("the C-arm runs navigation points step by step; use mode 'step'")
        lim = self.carm.limits_now
        for p in self.program_for(plan).points:
            why = lim.check_point(p.primary_deg, p.secondary_deg)
            if why:
                raise PreflightError(p.index, "carm", None, f"the connected C-arm's limits ({why})")

    async def prepare(self, plan: ScanPlan) -> None:
        """Load the program."""
        self.program = self.program_for(plan)
        await self.carm.load(self.program)
        self._point = -1

    def travel_s(self, start: Mapping[str, float], end: Mapping[str, float]) -> float:
        """Both angles turn at once at the configured speed (bridge points on the way not counted)."""
        turn = max(abs(end[k] - start[k]) for k in ("carm.primary", "carm.secondary"))
        scale = self.config.sim.time_scale if self.sim else 1.0
        return turn / self.config.limits.speed_deg_s / scale

    async def move_to(self, targets: Mapping[str, float], timeout_s: float) -> None:
        """Play the program on to the next point that takes a frame at ``targets`` (bridge points on the way)."""
        if self.program is None:
            raise AcquireError("the C-arm has no program loaded (prepare first)")
        want = (float(targets["carm.primary"]), float(targets["carm.secondary"]))
        points = self.program.points
        for target in range(self._point + 1, len(points)):
            pt = points[target]
            if (
                pt.acquire
                and abs(pt.primary_deg - want[0]) <= ANGLE_TOL_DEG
                and abs(pt.secondary_deg - want[1]) <= ANGLE_TOL_DEG
            ):
                break
        else:
            raise AcquireError(
                f"no program point after {self._point} takes a frame at primary {want[0]:.3f} deg, "
                f"secondary {want[1]:.3f} deg"
            )
        mark = self._stops
        for p in range(self._point + 1, target + 1):  # bridge points (no frame), then the frame's point
            if self._stops != mark:
                raise AcquireError(f"the C-arm was stopped on its way to program point {target}; it stays where it is")
            await within(
                timeout_s,
                self.carm.name,
                f"did not reach program point {p}",
                "motion.move_timeout_s",
                self.carm.goto(p),
            )
            self._point = p

    async def acquire(
        self, image_key: int, after_exposure: Callable[[], None] | None = None, *, next_exposure_s: float | None = None
    ) -> Frame:
        """A dark, flat or projection frame (the C-arm exposes and reads out in one action; it keeps its own source
        ready, whatever ``next_exposure_s`` says)."""
        stall, ex = self.config.stall, self.config.exposure
        bound = stall.frame_s + stall.exposure_s + (ex.exposure_ms + ex.prep_ms) / 1000.0
        if image_key in (ImageKey.DARK, ImageKey.FLAT):
            take = self.carm.acquire_dark if image_key == ImageKey.DARK else self.carm.acquire_flat
            what = f"delivered no {'dark' if image_key == ImageKey.DARK else 'flat'} frame"
            return (await within(bound, self.carm.name, what, "stall.frame_s", take(1)))[0]
        frame = await within(
            bound,
            self.carm.name,
            "delivered no frame for its exposure",
            "stall.frame_s + stall.exposure_s",
            self.carm.expose(),
        )
        if after_exposure is not None:
            after_exposure()
        return frame

    async def read_positions(self) -> dict[str, float]:
        """Encoded primary and secondary angles."""
        pos = await self.carm.position()
        return {"carm.primary": float(pos["primary"]), "carm.secondary": float(pos["secondary"])}

    async def stop_all(self, *, interrupted: bool = False) -> None:
        """Halt the C-arm now (on a connection of its own); never raises."""
        self._stops += 1
        for exc in await stop_devices([self.carm]):
            log.error("stop_all: %s", exc)

    async def restore(self) -> None:
        """Nothing stays on: the C-arm exposes per frame."""

    async def close(self) -> None:
        """Stop the arm and disconnect."""
        await self.stop_all()
        with contextlib.suppress(Exception):
            await self.carm.close()


@contextlib.asynccontextmanager
async def open_carm(
    cfg: CArmConfig, *, sim: bool, links: Mapping[str, DeviceLink] | None = None
) -> AsyncIterator[CArmRig]:
    """Connect the C-arm of ``cfg`` (its twin in-process when ``sim``; ``links`` overrides where it is reached)."""
    link = (links or carm_links(cfg, sim=sim))["carm"]
    rig = CArmRig(cfg, await open_device("carm", "carm", link.uri, **link.options), sim=sim)
    try:
        yield rig
    finally:
        await rig.close()


def carm_links(cfg: CArmConfig, *, sim: bool) -> dict[str, DeviceLink]:
    """Where the C-arm is reached: its configured URI, or ``sim://carm`` with the twin's options."""
    det = cfg.geometry.detector
    twin = {
        "rows": det.rows,
        "cols": det.cols,
        "sad_mm": cfg.geometry.sad_mm,
        "sdd_mm": cfg.geometry.sdd_mm,
        "seed": cfg.sim.seed,
        "phantom": cfg.sim.imaged(),
        "detector_model": cfg.sim.detector_model(),
        "beam": cfg.sim.beam_model(),
    }
    if not sim:  # a sim:// twin configured here runs at real speed
        return {"carm": configured_link(cfg.devices.carm, {}, twin)}
    return {"carm": DeviceLink(f"sim://{SIM_WORLD}", {**twin, "time_scale": cfg.sim.time_scale})}
