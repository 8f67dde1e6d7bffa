"""Pre-flight: every frame of a plan checked against every limit before anything moves.

The checks work on the plan's axis targets (keyed like ``/frames/commanded``), so each rig
combines the ones it needs: :func:`bench_preflight` for the bench, the C-arm rig checks its
navigation program against the connected arm.
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable, Mapping, Sequence

import numpy as np

from acquire.config import BenchConfig
from acquire.errors import PreflightError
from acquire.kinematics import HEXAPOD_AXES, STAGE_AXIS
from acquire.plan import ScanPlan, sweep_run_up_deg, sweep_speed, sweeps, swept_steps

# async check of full hexapod poses {'X': mm, ..., 'U': deg, ...}; returns the index of the first unreachable one
WorkspaceCheck = Callable[[Sequence[Mapping[str, float]]], Awaitable[int | None]]
Range = tuple[float, float]


def _first_outside(values: np.ndarray, low: float, high: float, tol: float = 1e-9) -> int | None:
    bad = np.flatnonzero((values < low - tol) | (values > high + tol) | ~np.isfinite(values))
    return int(bad[0]) if bad.size else None


def errors_note(plan: ScanPlan) -> str:
    """What a refusal says of the plan's injected motion errors (empty when it has none): they are part of every
    target, and how to run without them."""
    if not np.any(plan.errors):
        return ""
    try:
        name = json.loads(plan.error_profile).get("name", plan.error_profile)
    except (ValueError, AttributeError):
        name = plan.error_profile
    whose = f"the {name!r} error profile's" if name not in ("", "none") else "the plan's"
    scale = ", as large as the orbit's step per frame (fewer frames, larger errors)" if name == "bench" else ""
    return f"The targets include {whose} injected motion errors{scale}; another seed, more frames or no error profile may pass"


def check_limits(plan: ScanPlan, sources: Mapping[str, Mapping[str, Range]]) -> None:
    """Refuse the plan at its first frame that leaves a range of any source (``configured``, ``controller``)."""
    worst: tuple[int, str, float, str] | None = None
    for axis, values in plan.targets.items():
        for label, limits in sources.items():
            if axis not in limits:
                continue
            lo, hi = limits[axis]
            i = _first_outside(values, lo, hi)
            if i is not None and (worst is None or i < worst[0]):
                worst = (i, axis, float(values[i]), f"the {label} range [{lo:g}, {hi:g}]")
    if worst is not None:
        i, axis, value, allowed = worst
        raise PreflightError(i, axis, value, allowed, plan.units.get(axis, ""), errors_note(plan))


def check_speeds(plan: ScanPlan, config: BenchConfig, frame_rate_hz: float) -> None:
    """Continuous mode: refuse frames whose step from the previous one, made while the stage sweeps between two
    triggers (:func:`acquire.plan.swept_steps`), needs more than the allowed speeds. Moves between sweeps (a rewind
    after a full turn, the start of the next arc) are moves of their own, at the configured velocities."""
    dt = 1.0 / frame_rate_hz
    swept = swept_steps(plan)
    stage_speed = np.where(swept, np.abs(np.diff(plan.targets[STAGE_AXIS])) / dt, 0.0)
    i = _first_outside(stage_speed, 0.0, config.limits.stage_velocity_deg_s)
    xyz = np.stack([plan.targets[f"hexapod.{a}"] for a in HEXAPOD_AXES[:3]], axis=1)
    lin = np.where(swept, np.linalg.norm(np.diff(xyz, axis=0), axis=1) / dt, 0.0)
    j = _first_outside(lin, 0.0, config.limits.hexapod_velocity_mm_s)
    candidates = [
        (k + 1, n, v, lim)
        for k, n, v, lim in (
            (i, "rotation_stage velocity", stage_speed, config.limits.stage_velocity_deg_s),
            (j, "hexapod linear velocity", lin, config.limits.hexapod_velocity_mm_s),
        )
        if k is not None
    ]
    if candidates:
        k, name, v, lim = min(candidates, key=lambda c: c[0])
        unit = "deg/s" if "rotation" in name else "mm/s"
        raise PreflightError(
            k,
            name,
            float(v[k - 1]),
            f"the allowed [0, {lim:g}] at {frame_rate_hz:g} frames/s (a lower frame rate, or step mode)",
            unit,
        )


def check_run_ups(plan: ScanPlan, sources: Mapping[str, Mapping[str, Range]], frame_rate_hz: float) -> None:
    """Continuous mode: refuse a sweep whose run-up before its first trigger angle, or run-on past its last
    (:func:`acquire.plan.sweep_run_up_deg`), leaves a range of the sweep axis (the stage) of any source."""
    stage = plan.targets[STAGE_AXIS]
    for start, end in sweeps(plan):
        run = float(np.sign(stage[end] - stage[start])) * sweep_run_up_deg(
            sweep_speed(stage, start, end, frame_rate_hz)
        )
        for frame, value, what in (
            (start, stage[start] - run, "run-up before"),
            (end, stage[end] + run, "run-on past"),
        ):
            for label, limits in sources.items():
                if STAGE_AXIS in limits:
                    lo, hi = limits[STAGE_AXIS]
                    if not lo <= value <= hi:
                        raise PreflightError(
                            frame,
                            f"{STAGE_AXIS} ({what} the sweep's trigger angle at {frame_rate_hz:g} frames/s)",
                            float(value),
                            f"the {label} range [{lo:g}, {hi:g}]",
                            plan.units.get(STAGE_AXIS, ""),
                            "A lower frame rate shortens it, or step mode needs none",
                        )


async def check_workspace(plan: ScanPlan, workspace_check: WorkspaceCheck) -> None:
    """Every full hexapod pose against the controller's coupled workspace (``VMO?``)."""
    columns = [plan.targets[f"hexapod.{a}"] for a in HEXAPOD_AXES]
    poses = [{a: float(col[n]) for a, col in zip(HEXAPOD_AXES, columns)} for n in range(plan.n_frames)]
    i = await workspace_check(poses)
    if i is not None:
        p = poses[i]
        pose_txt = ", ".join(f"{a}={p[a]:.3f}" for a in HEXAPOD_AXES)
        raise PreflightError(
            i,
            "hexapod (coupled workspace)",
            None,
            f"the controller's workspace (VMO? refused pose {pose_txt})",
            note=errors_note(plan),
        )


async def bench_preflight(
    plan: ScanPlan,
    config: BenchConfig,
    *,
    device_limits: Mapping[str, Range] | None = None,
    workspace_check: WorkspaceCheck | None = None,
    mode: str = "step",
    frame_rate_hz: float | None = None,
) -> None:
    """Check a bench plan (errors included) against every limit; raise :class:`PreflightError` on the first failure."""
    sources: dict[str, Mapping[str, Range]] = {"configured": config.axis_limits()}
    if device_limits:
        sources["controller"] = device_limits
    check_limits(plan, sources)
    if mode == "continuous":
        check_speeds(plan, config, frame_rate_hz or config.exposure.frame_rate_hz)
        check_run_ups(plan, sources, frame_rate_hz or config.exposure.frame_rate_hz)
    if workspace_check is not None:
        await check_workspace(plan, workspace_check)
