"""Continuous mode of the scan engine: darks and flats step by step, projections while the sweep axis turns at
constant speed, each exposed as the sweep passes its angle with the X-ray source kept ready, a frame that came
too far from its angle taken again from a new start of its sweep.

:class:`ContinuousMode` is a part of :class:`acquire.engine.ScanEngine` (its order of actions and safety rules
are the engine's: frame boundaries, exposures and records go through it); the waits at angles are functions of
their own.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Protocol

import numpy as np

from acquire.config import MotionConfig
from acquire.errors import AcquireError
from acquire.plan import FramePlan, ScanPlan, sweep_end, sweep_run_up_deg, sweep_speed
from acquire.records import FrameRecord
from acquire.rig import PreparingRig, Rig, SweepRig
from orbitct.scanfile.keys import ImageKey

log = logging.getLogger("acquire.engine")  # the engine's warnings, wherever its parts live


class SweepingEngine(Protocol):
    """What continuous mode uses of the engine."""

    rig: Rig
    plan: ScanPlan
    motion: MotionConfig
    frame_rate_hz: float
    _resume: asyncio.Event
    _prepare_s: float
    _late_restarts: int

    async def _boundary(self) -> None: ...
    def _check_abort(self) -> None: ...
    def _record_motion(self, t_start: float) -> None: ...
    async def _shoot(self, f: FramePlan, t0: float) -> None: ...
    async def _expose(
        self, f: FramePlan, t0: float, *, sweeping: bool = False, next_exposure_s: float | None = None
    ) -> FrameRecord: ...
    def _record(self, rec: FrameRecord, t0: float) -> None: ...


class ContinuousMode:
    """The engine's continuous mode (a base of :class:`acquire.engine.ScanEngine`)."""

    async def _run_continuous(self: SweepingEngine, t0: float) -> None:
        """Darks/flats step-wise; projections while the sweep axis turns at constant speed, triggered at angles."""
        rig: SweepRig = self.rig  # type: ignore[assignment]
        plan = self.plan
        proj = np.flatnonzero(plan.image_key == ImageKey.PROJECTION)
        first, last_p = int(proj[0]), int(proj[-1])
        timeout = self.motion.move_timeout_s
        for i in range(first):
            await self._boundary()
            f = plan.frame(i)
            if i == 0:
                await rig.move_to(f.targets, timeout)
            await self._shoot(f, t0)
        sweep = plan.targets[rig.sweep_axis]
        idx, late_at = first, None  # late_at: the frame whose sweep was last started anew because it came late
        while idx <= last_p:
            await self._boundary()
            f = plan.frame(idx)
            end = sweep_end(sweep, idx, last_p)
            t_m = time.monotonic()
            if end == idx:  # the sweep axis stays here (a tilt-only arc): step and shoot
                await rig.move_to(f.targets, timeout)
                self._record_motion(t_m)
                await self._shoot(f, t0)
                idx += 1
                continue
            # a sweep: position just before the first trigger angle, then turn at constant speed
            velocity = sweep_speed(sweep, idx, end, self.frame_rate_hz)
            direction = float(np.sign(sweep[end] - sweep[idx]))
            lead = direction * sweep_run_up_deg(velocity)
            await rig.move_to({**f.targets, rig.sweep_axis: float(sweep[idx] - lead)}, timeout)
            if isinstance(rig, PreparingRig):  # the first angle comes too soon after the start to get ready on the way
                await rig.prepare_exposure()
            await rig.start_sweep(float(sweep[end] + lead), velocity)
            self._record_motion(t_m)
            while idx <= end:
                f = plan.frame(idx)
                t_m = time.monotonic()
                past = await _ready_at_angle(self, rig, float(sweep[idx]), direction, velocity, timeout)
                self._record_motion(t_m)
                step = abs(float(sweep[idx + 1] - sweep[idx])) if idx < end else abs(float(sweep[idx] - sweep[idx - 1]))
                if past > 0.5 * step:  # the sweep ran ahead of the exposures: this one would be nearer the next angle
                    await _start_sweep_anew(self, rig, idx, past, step, late_at)
                    late_at = idx
                    break
                nxt_s = 1.0 / self.frame_rate_hz if idx < end else None
                rec = await self._expose(f, t0, sweeping=True, next_exposure_s=nxt_s)
                off = (rec.encoders[rig.sweep_axis] - float(sweep[idx])) * direction
                if abs(off) > 0.5 * step:  # exposed too far from its angle after all: not recorded, taken again
                    await _start_sweep_anew(self, rig, idx, off, step, late_at, exposed=True)
                    late_at = idx
                    break
                self._record(rec, t0)
                idx += 1
                if idx <= end:
                    nxt = plan.frame(idx).targets
                    await rig.start_move({a: v for a, v in nxt.items() if a != rig.sweep_axis})
                if not self._resume.is_set():  # pause: stop the sweep, restart from here on resume
                    await rig.stop_all()
                    break
        for i in range(last_p + 1, plan.n_frames):
            await self._boundary()
            await self._shoot(plan.frame(i), t0)


async def _start_sweep_anew(
    engine: SweepingEngine,
    rig: SweepRig,
    idx: int,
    past_deg: float,
    step_deg: float,
    late_at: int | None,
    *,
    exposed: bool = False,
) -> None:
    """Frame ``idx`` is ready ``past_deg`` past its angle, more than half a step (``exposed``: its exposure's
    middle was that far from it, and the frame is dropped): stop the sweep so that it starts again from this
    frame (a frame exposed there would be recorded at the wrong angle). Late again right after the last such
    start (``late_at``): the exposures cannot keep up, and the scan ends."""
    what = f"exposed {past_deg:.2f} deg from its angle" if exposed else f"ready {past_deg:.2f} deg past its angle"
    if late_at is not None and 0 <= idx - late_at <= 1:
        anew = (
            "again, after its sweep was started anew from it"
            if idx == late_at
            else f"right after its sweep was started anew at frame {late_at}, which had been late too"
        )
        raise AcquireError(
            f"continuous mode: frame {idx} was {what} (at most half a step, {0.5 * step_deg:.2f} deg, is "
            f"allowed) {anew}; the exposures cannot keep up at {engine.frame_rate_hz:g} frames/s: a lower frame "
            "rate, or step mode"
        )
    engine._late_restarts += 1
    dropped = " and was not recorded" if exposed else ""
    log.warning("continuous mode: frame %d %s%s; its sweep starts again from it", idx, what, dropped)
    await rig.stop_all()


async def _ready_at_angle(
    engine: SweepingEngine, rig: SweepRig, target: float, direction: float, velocity: float, timeout_s: float
) -> float:
    """Wait until the sweep reaches ``target`` with the X-ray source ready: a :class:`PreparingRig`'s
    preparation starts its preparation time (and a fifth more) before the angle, so the exposure is not late
    by a preparation while the stage turns on (a DCArc at 4 frames/s on the simulated bench had 2 of 3
    projections exposed about 5 degrees past their angle, the read-backs taken at the angle). Once ready, the
    source is asked again every quarter preparation until the angle: the generator holds it only its hold
    time (about a preparation) from each request, and the sweep may take longer to get there than its speed
    says (the first angle of a sweep, still accelerating, was reached 160 ms after a 200 ms hold began, and a
    process held up 40 ms more exposed it a whole preparation late). Returns how far past ``target`` the sweep
    was once ready (deg)."""
    prep_s = rig.prep_s if isinstance(rig, PreparingRig) else 0.0
    if prep_s <= 0:
        return await _wait_for_angle(engine, rig, target, direction, velocity, timeout_s)
    lead = direction * velocity * prep_s
    await _wait_for_angle(engine, rig, target - 1.2 * lead, direction, velocity, timeout_s)
    t_p = time.monotonic()
    await rig.prepare_exposure()  # type: ignore[attr-defined]
    engine._prepare_s += time.monotonic() - t_p
    started = time.monotonic()
    while True:
        until = time.monotonic() + 0.25 * prep_s
        past = await _angle_passed(engine, rig, target, direction, velocity, timeout_s, started, until)
        if past is not None:
            return past
        t_p = time.monotonic()
        await rig.prepare_exposure()  # type: ignore[attr-defined]  # ready: one short exchange renews the hold
        engine._prepare_s += time.monotonic() - t_p


async def _wait_for_angle(
    engine: SweepingEngine, rig: SweepRig, target: float, direction: float, velocity: float, timeout_s: float
) -> float:
    """Wait until the sweep passes ``target``; how far past it (deg) it was when seen there."""
    started = time.monotonic()
    while True:
        past = await _angle_passed(engine, rig, target, direction, velocity, timeout_s, started, started + timeout_s)
        if past is not None:
            return past


async def _angle_passed(
    engine: SweepingEngine,
    rig: SweepRig,
    target: float,
    direction: float,
    velocity: float,
    timeout_s: float,
    started: float,
    until: float,
) -> float | None:
    """How far past ``target`` (deg) the sweep was when seen there, or None if it is not there by ``until``
    (``time.monotonic()``); an error once ``timeout_s`` from ``started`` has gone by."""
    while True:
        engine._check_abort()
        pos = await rig.sweep_position()
        remaining = (target - pos) * direction
        if remaining <= 0:
            return -remaining
        now = time.monotonic()
        if now > started + timeout_s:
            raise AcquireError(
                f"continuous mode: {rig.sweep_axis} did not reach the trigger angle {target:.3f} deg "
                f"within {timeout_s:g} s (at {pos:.3f} deg)"
            )
        if now >= until:
            return None
        await asyncio.sleep(min(max(remaining / velocity * 0.8, 0.0002), 0.05, until - now))
