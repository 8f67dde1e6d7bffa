"""C-arm path: export the orbit as a navigation-point program, play it on the C-arm, record the same way.

The C-arm carries source and detector; its own systematic errors (tilt sag, isocenter
drift, panel rotation) are what calibration has to find, so no error is injected here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from acquire.config import CArmConfig
from acquire.engine import ScanEngine
from acquire.errors import AcquireError, PreflightError
from acquire.plan import ScanPlan, _layout
from acquire.recorder import ScanRecorder
from devices.carm import CArm
from devices.carm_program import CArmLimits, InfeasibleOrbitError, NavProgram, export_program
from devices.factory import open_device
from devices.factory import stop_all as stop_devices
from orbitct.geometry import ViewGeometry
from orbitct.orbits import Orbit
from orbitct.progress import ProgressCallback
from orbitct.scanfile.keys import ImageKey

if TYPE_CHECKING:
    from acquire.runner import ScanRequest, ScanResult, ScanRunner

log = logging.getLogger(__name__)
SIM_WORLD = "carm"


def carm_limits(cfg: CArmConfig) -> CArmLimits:
    """The exporter's limits from a C-arm configuration."""
    lim = cfg.limits
    return CArmLimits(primary_deg=tuple(lim.primary_deg), secondary_deg=tuple(lim.secondary_deg),
                      max_step_deg=lim.max_step_deg, max_speed_deg_s=lim.speed_deg_s)


def export_orbit(orbit: Orbit, cfg: CArmConfig) -> NavProgram:
    """Navigation points for ``orbit``; an infeasible orbit raises :class:`PreflightError` naming the first bad frame."""
    try:
        return export_program(orbit, carm_limits(cfg), speed_deg_s=cfg.limits.speed_deg_s)
    except InfeasibleOrbitError as exc:
        raise PreflightError(exc.index, "carm", None, f"the C-arm's limits ({exc})") from None


def plan_carm_scan(cfg: CArmConfig, orbit: Orbit) -> ScanPlan:
    """Frames of a C-arm scan: darks/flats around the projections, nominal C-arm views."""
    cf = cfg.calibration_frames
    keys, view, pose = _layout(orbit.n_frames, cf.darks_before, cf.flats_before, cf.darks_after, cf.flats_after)
    nominal = np.full((keys.size, 12), np.nan)
    nominal[keys == ImageKey.PROJECTION] = cfg.geometry.carm_views(orbit.theta, orbit.phi).vectors
    n = keys.size
    return ScanPlan(
        image_key=keys, view=view, theta_rad=orbit.theta[pose], phi_rad=orbit.phi[pose], errors=np.zeros((n, 6)),
        stage_rad=np.zeros(n), hexapod=np.zeros((n, 6)), nominal=ViewGeometry(nominal, cfg.geometry.detector.panel()),
        orbit_name=orbit.name, orbit_params=dict(orbit.params), error_profile=json.dumps({"name": "carm-systematic"}),
        config=cfg.model_dump(mode="json"),
    )


class CArmBench:
    """A connected C-arm behind the calls the engine needs."""

    def __init__(self, carm: CArm, *, sim: bool, phantom: Any = None) -> None:
        self.carm = carm
        self.sim = sim
        self.phantom = phantom
        self.axes = {"carm.primary": "deg", "carm.secondary": "deg"}
        self._last_truth: NDArray[np.float64] | None = None

    async def goto(self, point: int) -> None:
        """Move to navigation point ``point`` and wait on target."""
        await self.carm.goto(point)

    async def read_positions(self) -> dict[str, float]:
        """Encoded primary and secondary angles."""
        pos = await self.carm.position()
        return {"carm.primary": float(pos["primary"]), "carm.secondary": float(pos["secondary"])}

    async def acquire(self, image_key: int) -> tuple[NDArray[Any], int]:
        """A dark, flat or projection frame."""
        self._last_truth = None
        if image_key == ImageKey.DARK:
            frame = (await self.carm.acquire_dark(1))[0]
        elif image_key == ImageKey.FLAT:
            frame = (await self.carm.acquire_flat(1))[0]
        else:
            frame = await self.carm.expose()
            tv = frame.meta.get("truth_vectors") if self.sim else None
            self._last_truth = np.asarray(tv, dtype=float) if tv is not None else None
        return frame.data, int(frame.number)

    def last_true_vector(self) -> NDArray[np.float64] | None:
        """The true view of the last projection (twins only)."""
        return self._last_truth

    def true_pose(self) -> None:
        """Not used: the C-arm twin reports the true view with each frame."""
        return None

    def truth_extras(self) -> dict[str, Any]:
        """True marker centres and phantom description (twins only)."""
        if not self.sim or self.phantom is None:
            return {}
        return {"markers_xyz": np.asarray(self.phantom.markers_xyz), "phantom": self.phantom.to_json()}

    async def xray_off(self) -> None:
        """The C-arm twin exposes per frame only; nothing stays on."""

    async def stop_all(self) -> None:
        """Halt the C-arm now; never raises."""
        for exc in await stop_devices([self.carm]):
            log.error("stop_all: %s", exc)

    async def restore_stage_velocity(self) -> None:
        """Nothing to restore on a C-arm."""

    def mark_interrupted(self) -> None:
        """The C-arm driver stops on its own connection; nothing to resynchronise."""


class CArmEngine(ScanEngine):
    """The engine's safety and recording rules, stepping through navigation points."""

    def __init__(self, bench: CArmBench, plan: ScanPlan, config: CArmConfig, program: NavProgram, **kw: Any) -> None:
        super().__init__(bench, plan, config, mode="step", **kw)  # type: ignore[arg-type]
        self.program = program
        self._acquire_points = [p.index for p in program.points if p.acquire]

    async def _preflight(self) -> None:
        lim = self.bench.carm.limits_now  # type: ignore[attr-defined]
        for p in self.program.points:
            why = lim.check_point(p.primary_deg, p.secondary_deg)
            if why:
                raise PreflightError(p.index, "carm", None, f"the connected C-arm's limits ({why})")

    async def _prepare(self) -> None:
        await self.bench.carm.load(self.program)  # type: ignore[attr-defined]

    def _start_extra(self) -> dict[str, Any]:
        return {"navigation_points": len(self.program.points), "speed_deg_s": self.config.limits.speed_deg_s}

    def _commanded(self, f: Any) -> dict[str, float]:
        return {"carm.primary": float(np.degrees(f.theta_rad)), "carm.secondary": float(np.degrees(f.phi_rad))}

    async def _execute(self, t0: float) -> None:
        bench: CArmBench = self.bench  # type: ignore[assignment]
        point = -1  # last program point visited
        for f in self.plan:
            await self._boundary()
            if f.view >= 0:  # darks and flats are taken wherever the arm is
                target = self._acquire_points[f.view]
                t_m = time.monotonic()
                for p in range(point + 1, target + 1):  # bridge points (no frame), then the frame's point
                    self._check_abort()
                    await bench.goto(p)
                self._record_motion(t_m)
                point = target
            await self._shoot(f, t0, self._commanded(f))


@contextlib.asynccontextmanager
async def open_carm(cfg: CArmConfig, *, sim: bool) -> AsyncIterator[CArmBench]:
    """Connect the C-arm of ``cfg`` (its twin in-process when ``sim``)."""
    det = cfg.geometry.detector
    uri = f"sim://{SIM_WORLD}" if sim else cfg.devices.carm
    opts: dict[str, Any] = {"rows": det.rows, "cols": det.cols, "sad_mm": cfg.geometry.sad_mm,
                            "sdd_mm": cfg.geometry.sdd_mm}
    phantom = None
    if sim:
        from orbitct.phantoms.experiments import experiment_phantom

        phantom = experiment_phantom(cfg.sim.phantom, seed=cfg.sim.seed)
        opts.update(time_scale=cfg.sim.time_scale, seed=cfg.sim.seed, phantom=cfg.sim.phantom)
    else:
        opts = {}
    carm = await open_device("carm", "carm", uri, **opts)
    try:
        yield CArmBench(carm, sim=sim, phantom=phantom)
    finally:
        with contextlib.suppress(Exception):
            await stop_devices([carm])
        with contextlib.suppress(Exception):
            await carm.close()


async def run_carm_scan(req: "ScanRequest", cfg: CArmConfig, *, progress: ProgressCallback | None = None,
                        runner: "ScanRunner | None" = None) -> "ScanResult":
    """Export, load and play the orbit on the C-arm, recording every frame into ``req.out``."""
    from acquire.runner import ScanResult, make_orbit_and_errors

    if req.mode != "step":
        raise AcquireError("the C-arm path runs navigation points step by step; use mode 'step'")
    orbit, _, _ = make_orbit_and_errors(dataclasses.replace(req, errors="none", error_params={}))
    program = export_orbit(orbit, cfg)
    out = Path(req.out)
    if out.exists() and not req.overwrite:
        raise AcquireError(f"{out}: already exists (use overwrite to replace it)")
    program.write(out.with_suffix(".nav.json"))
    program.write(out.with_suffix(".nav.csv"))
    plan = plan_carm_scan(cfg, orbit)
    recorder = ScanRecorder(out, overwrite=req.overwrite, marker_diameter_mm=cfg.sim.bb_diameter_mm if req.sim else None)
    async with open_carm(cfg, sim=req.sim) as bench:
        engine = CArmEngine(bench, plan, cfg, program, subscribers=[recorder], progress=progress)
        if runner is not None:
            runner._attach(engine)
        outcome = await engine.run()
    return ScanResult(out, outcome.status, outcome.reason, outcome.n_frames, outcome.n_planned, outcome.elapsed_s,
                      engine.timing)
