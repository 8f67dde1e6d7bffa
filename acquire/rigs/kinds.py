"""What differs between the bench and the C-arm before and around a scan, asked of one object per kind of rig.

The runner plans, records and connects through :func:`rig_kind`; it never branches on the configuration's class.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from acquire.config import BenchConfig, CArmConfig
from acquire.plan import ScanPlan, plan_bench_scan, plan_carm_scan
from acquire.rig import Rig
from acquire.rigs.bench import bench_links, open_bench
from acquire.rigs.carm import carm_links, export_orbit, open_carm
from acquire.rigs.links import DeviceLink
from orbitct.orbits import Orbit, make_orbit


class RigKind(Protocol):
    """The bench or the C-arm: how its scans are planned, recorded and connected."""

    #: what the operator calls it
    name: str
    #: motion errors can be injected into its scans (a C-arm's own errors are what is measured)
    injects_errors: bool
    #: the scan modes it runs
    modes: tuple[str, ...]

    def plan(self, config: Any, orbit: Orbit, errors: NDArray[np.float64], profile: Mapping[str, Any]) -> ScanPlan:
        """The frames of a scan of ``orbit`` (with ``errors``, (N, 6), described by ``profile``)."""
        ...

    def write_program(self, config: Any, plan: ScanPlan, out: Path) -> None:
        """Write beside the scan file what the machine itself plays, if anything."""
        ...

    def recorded(self, config: Any, plan: ScanPlan, frame_rate_hz: float) -> dict[str, Any]:
        """What a scan records about its rig in ``/acquisition`` besides mode and errors."""
        ...

    def links(self, config: Any, *, sim: bool) -> dict[str, DeviceLink]:
        """Where each device is reached (``sim``: ``sim://`` URIs carrying twin and driver options)."""
        ...

    def open(
        self, config: Any, *, sim: bool, links: Mapping[str, DeviceLink] | None
    ) -> contextlib.AbstractAsyncContextManager[Rig]:
        """Connect the rig (its twins in-process when ``sim``, or at ``links``); closed on exit."""
        ...


class BenchKind:
    """The test bench: hexapod on a rotation stage, generator and panel; step and continuous scans."""

    name = "bench"
    injects_errors = True
    modes: tuple[str, ...] = ("step", "continuous")

    def plan(
        self, config: BenchConfig, orbit: Orbit, errors: NDArray[np.float64], profile: Mapping[str, Any]
    ) -> ScanPlan:
        return plan_bench_scan(
            config,
            orbit.theta,
            orbit.phi,
            errors,
            orbit_name=orbit.name,
            orbit_params=orbit.params,
            error_profile=json.dumps(dict(profile), sort_keys=True),
        )

    def write_program(self, config: BenchConfig, plan: ScanPlan, out: Path) -> None:
        return None

    def recorded(self, config: BenchConfig, plan: ScanPlan, frame_rate_hz: float) -> dict[str, Any]:
        return {"frame_rate_hz": frame_rate_hz, "settle_ms": config.motion.settle_ms, "stack_order": config.stack.order}

    def links(self, config: BenchConfig, *, sim: bool) -> dict[str, DeviceLink]:
        return bench_links(config, sim=sim)

    def open(
        self, config: BenchConfig, *, sim: bool, links: Mapping[str, DeviceLink] | None
    ) -> contextlib.AbstractAsyncContextManager[Rig]:
        return open_bench(config, sim=sim, links=links)


class CArmKind:
    """A robotic C-arm driven through its navigation points; step scans only, no injected errors."""

    name = "C-arm"
    injects_errors = False
    modes: tuple[str, ...] = ("step",)

    def plan(
        self, config: CArmConfig, orbit: Orbit, errors: NDArray[np.float64], profile: Mapping[str, Any]
    ) -> ScanPlan:
        export_orbit(orbit, config)  # refuses an orbit outside the arm's ranges, naming the first bad frame
        return plan_carm_scan(config, orbit)

    def _program(self, config: CArmConfig, plan: ScanPlan) -> Any:
        return export_orbit(make_orbit(plan.orbit_name, **dict(plan.orbit_params)), config)

    def write_program(self, config: CArmConfig, plan: ScanPlan, out: Path) -> None:
        program = self._program(config, plan)  # the navigation program, as the C-arm plays it
        out.parent.mkdir(parents=True, exist_ok=True)
        program.write(out.with_suffix(".nav.json"))
        program.write(out.with_suffix(".nav.csv"))

    def recorded(self, config: CArmConfig, plan: ScanPlan, frame_rate_hz: float) -> dict[str, Any]:
        return {"navigation_points": len(self._program(config, plan).points), "speed_deg_s": config.limits.speed_deg_s}

    def links(self, config: CArmConfig, *, sim: bool) -> dict[str, DeviceLink]:
        return carm_links(config, sim=sim)

    def open(
        self, config: CArmConfig, *, sim: bool, links: Mapping[str, DeviceLink] | None
    ) -> contextlib.AbstractAsyncContextManager[Rig]:
        return open_carm(config, sim=sim, links=links)


_KINDS: dict[type, RigKind] = {BenchConfig: BenchKind(), CArmConfig: CArmKind()}


def rig_kind(config: BenchConfig | CArmConfig) -> RigKind:
    """The kind of rig a configuration describes."""
    for cls, kind in _KINDS.items():
        if isinstance(config, cls):
            return kind
    raise TypeError(f"no rig for a configuration of type {type(config).__name__}")
