"""Pre-flight: every frame of a plan checked against every limit before anything moves."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping, Sequence

import numpy as np

from acquire.config import BenchConfig
from acquire.errors import PreflightError
from acquire.kinematics import HEXAPOD_AXES, HEXAPOD_UNITS
from acquire.plan import ScanPlan

# async check of full hexapod poses {'X': mm, ..., 'U': deg, ...}; returns the index of the first unreachable one
WorkspaceCheck = Callable[[Sequence[Mapping[str, float]]], Awaitable[int | None]]

STAGE_AXIS = "rotation_stage"


def _first_outside(values: np.ndarray, low: float, high: float, tol: float = 1e-9) -> int | None:
    bad = np.flatnonzero((values < low - tol) | (values > high + tol) | ~np.isfinite(values))
    return int(bad[0]) if bad.size else None


def axis_targets_user(plan: ScanPlan) -> dict[str, np.ndarray]:
    """Per-frame targets in controller units: ``rotation_stage`` (deg) and hexapod ``X..W`` (mm, deg)."""
    out = {STAGE_AXIS: np.degrees(plan.stage_rad)}
    for i, a in enumerate(HEXAPOD_AXES):
        out[f"hexapod.{a}"] = plan.hexapod[:, i] if i < 3 else np.degrees(plan.hexapod[:, i])
    return out


def check_static_limits(
    plan: ScanPlan,
    config: BenchConfig,
    device_limits: Mapping[str, tuple[float, float]] | None = None,
) -> None:
    """Refuse the plan at its first frame that leaves a configured or controller soft limit."""
    targets = axis_targets_user(plan)
    hl = config.limits.hexapod
    limits: dict[str, tuple[float, float]] = {STAGE_AXIS: config.limits.rotation_stage_deg}
    limits.update({f"hexapod.{a}": getattr(hl, f"{a.lower()}_{u}") for a, u in zip(HEXAPOD_AXES, HEXAPOD_UNITS)})
    units = {STAGE_AXIS: "deg"} | {f"hexapod.{a}": u for a, u in zip(HEXAPOD_AXES, HEXAPOD_UNITS)}
    worst: tuple[int, str, float, str] | None = None
    for name, values in targets.items():
        sources = [("configured", limits[name])]
        if device_limits and name in device_limits:
            sources.append(("controller", device_limits[name]))
        for label, (lo, hi) in sources:
            i = _first_outside(values, lo, hi)
            if i is not None and (worst is None or i < worst[0]):
                worst = (i, name, float(values[i]), f"the {label} range [{lo:g}, {hi:g}]")
    if worst is not None:
        i, name, val, allowed = worst
        raise PreflightError(i, name, val, allowed, units[name])


def check_speeds(plan: ScanPlan, config: BenchConfig, frame_rate_hz: float) -> None:
    """Continuous mode: refuse frames whose step from the previous one needs more than the allowed speeds."""
    dt = 1.0 / frame_rate_hz
    stage_speed = np.abs(np.diff(np.degrees(plan.stage_rad))) / dt
    i = _first_outside(stage_speed, 0.0, config.limits.stage_velocity_deg_s)
    lin = np.linalg.norm(np.diff(plan.hexapod[:, :3], axis=0), axis=1) / dt
    j = _first_outside(lin, 0.0, config.limits.hexapod_velocity_mm_s)
    candidates = [(k + 1, n, v, lim) for k, n, v, lim in (
        (i, "rotation_stage velocity", stage_speed, config.limits.stage_velocity_deg_s),
        (j, "hexapod linear velocity", lin, config.limits.hexapod_velocity_mm_s),
    ) if k is not None]
    if candidates:
        k, name, v, lim = min(candidates, key=lambda c: c[0])
        unit = "deg/s" if "rotation" in name else "mm/s"
        raise PreflightError(k, name, float(v[k - 1]), f"the allowed [0, {lim:g}] at {frame_rate_hz:g} frames/s "
                             "(lower --frame-rate or use step mode)", unit)


async def preflight(
    plan: ScanPlan,
    config: BenchConfig,
    *,
    device_limits: Mapping[str, tuple[float, float]] | None = None,
    workspace_check: WorkspaceCheck | None = None,
    mode: str = "step",
    frame_rate_hz: float | None = None,
) -> None:
    """Check the whole plan (errors included) against every limit; raise :class:`PreflightError` on the first failure."""
    check_static_limits(plan, config, device_limits)
    if mode == "continuous":
        check_speeds(plan, config, frame_rate_hz or config.exposure.frame_rate_hz)
    if workspace_check is not None:
        poses = [
            {a: (float(q[k]) if k < 3 else float(np.degrees(q[k]))) for k, a in enumerate(HEXAPOD_AXES)}
            for q in plan.hexapod
        ]
        i = await workspace_check(poses)
        if i is not None:
            p = poses[i]
            pose_txt = ", ".join(f"{a}={p[a]:.3f}" for a in HEXAPOD_AXES)
            raise PreflightError(i, "hexapod (coupled workspace)", None,
                                 f"the controller's workspace (VMO? refused pose {pose_txt})")
