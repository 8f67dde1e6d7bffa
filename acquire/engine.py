"""How a plan runs on a rig: step-and-shoot or continuous, pause/resume, abort, guaranteed cleanup.

One engine serves every rig. The engine owns the order of actions and the safety rules; a
:class:`Rig` (the bench, the C-arm: ``acquire.rigs``) owns the device calls. Every exit path
(end of plan, device error, abort, Ctrl-C, task cancellation) halts every axis, switches
X-rays off and tells the subscribers how the scan ended, once. Continuous mode's sweeps are in
:mod:`acquire.continuous`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np
from numpy.typing import NDArray

from acquire.config import MotionConfig
from acquire.continuous import ContinuousMode
from acquire.errors import AcquireError, RefusedError, ScanAborted, ScanStateError
from acquire.pace import ScanPace
from acquire.plan import FramePlan, ScanPlan
from acquire.priority import steady_collection
from acquire.reasons import abort_reason, is_expected
from acquire.records import FrameRecord, ScanEnd, ScanStart, Subscriber
from acquire.rig import PreparingRig, Rig, SweepRig
from devices.frame_protocol import Frame
from orbitct.progress import ProgressCallback, report, report_expected
from orbitct.scanfile.keys import ImageKey

log = logging.getLogger(__name__)
MODES = ("step", "continuous")
PROJECTIONS_TIMED = 3  # projections measured before a step-mode scan says how long its frames take


@dataclass
class _Preparation:
    """A preparation of the source scheduled during a move: its task, and whether it has begun talking to it."""

    task: asyncio.Future[None]
    started: bool = False


@dataclass(frozen=True)
class ScanOutcome:
    """How a scan ended."""

    status: str
    reason: str
    n_frames: int
    n_planned: int
    elapsed_s: float


def _interpolated(
    before: Mapping[str, float], t_before: float, after: Mapping[str, float], t_after: float, t: float
) -> dict[str, float]:
    """Each axis's read-back at time ``t``, linear between one ``before`` and one ``after`` (never beyond them)."""
    w = min(max((t - t_before) / (t_after - t_before), 0.0), 1.0) if t_after > t_before else 0.0
    return {k: float(v) + w * (float(after[k]) - float(v)) if k in after else float(v) for k, v in before.items()}


class ScanEngine(ContinuousMode):
    """Runs one :class:`ScanPlan` on a :class:`Rig` and feeds subscribers; use :meth:`run` once."""

    def __init__(
        self,
        rig: Rig,
        plan: ScanPlan,
        *,
        motion: MotionConfig,
        frame_rate_hz: float,
        mode: str = "step",
        subscribers: Iterable[Subscriber] = (),
        progress: ProgressCallback | None = None,
        start_extra: Mapping[str, Any] | None = None,
        skip_preflight: bool = False,
        interlock: Callable[[], str | None] | None = None,
    ) -> None:
        if mode not in MODES:
            raise AcquireError(f"mode must be one of {MODES}, got {mode!r}")
        if mode == "continuous" and not isinstance(rig, SweepRig):
            raise AcquireError(f"{type(rig).__name__} runs step by step only; use mode 'step'")
        self.rig, self.plan, self.motion, self.mode = rig, plan, motion, mode
        self.subscribers = list(subscribers)
        self.progress = progress
        self.frame_rate_hz = float(frame_rate_hz)
        self.start_extra = dict(start_extra or {})
        self.skip_preflight = skip_preflight
        # why the scan must stop now, from outside the engine (a latched emergency stop), or None
        self.interlock = interlock
        self.state = "idle"
        self.n_done = 0
        self._abort_reason: str | None = None
        self._resume = asyncio.Event()
        self._resume.set()
        self._task: asyncio.Task[Any] | None = None
        self._stop_task: asyncio.Future[Any] | None = None
        self._motion_s = 0.0
        self._acquire_s = 0.0
        self._readback_s = 0.0
        self._record_s = 0.0
        self._prepare_s = 0.0
        self._late_restarts = 0
        self._run_s = 0.0
        self._move_s: float | None = None  # estimated move + settle to the next projection
        self._pace: ScanPace | None = None  # step mode: what the rest of the frames take, learned as they run

    # ------------------------------------------------------------- control
    def pause(self) -> None:
        """Stop before the next frame (the current frame completes)."""
        if self.state in ("complete", "aborted"):
            raise ScanStateError(f"cannot pause a scan that is {self.state}")
        self._resume.clear()

    def resume(self) -> None:
        """Continue a paused scan; never one that is being aborted or while the interlock holds (it stays paused and
        ends at its next step)."""
        if self._abort_reason is not None or (self.interlock is not None and self.interlock() is not None):
            return
        self._resume.set()

    def abort(self, reason: str = "aborted by the operator") -> None:
        """Stop now: halt every axis, X-rays off, mark the scan aborted with ``reason``.

        The halt is sent at once, concurrently with whatever the scan is doing; the
        frame loop then ends at its next step (a halted move or exposure fails at once).
        """
        if self.state in ("complete", "aborted") or self._abort_reason is not None:
            return
        self._abort_reason = reason
        self._resume.set()
        if self.state in ("running", "paused"):
            self._stop_task = asyncio.ensure_future(self.rig.stop_all())

    def _check_abort(self) -> None:
        if self._abort_reason is None and self.interlock is not None:
            self._abort_reason = self.interlock()
        if self._abort_reason is not None:
            raise ScanAborted(self._abort_reason)

    def _why(self, exc: BaseException) -> str:
        """The reason a scan ended on ``exc``: an abort or a latched stop outranks what it caused (a device
        refusing because the stop switched it off)."""
        if self._abort_reason is None and self.interlock is not None:
            self._abort_reason = self.interlock()
        return self._abort_reason or abort_reason(exc)

    @property
    def paused(self) -> bool:
        """Whether the scan waits at a frame boundary."""
        return self.state == "paused"

    @property
    def timing(self) -> dict[str, float]:
        """Seconds of the frame loop: total, in detector acquisition (exposure, rendering, readout), in
        commanded moves and settling, and the rest (executor and recorder overhead), of which read-backs
        and recording (subscribers' ``on_frame``) and waiting, after a move, for the source's preparation."""
        rest = self._run_s - self._acquire_s - self._motion_s
        return {
            "run_s": self._run_s,
            "acquire_s": self._acquire_s,
            "motion_s": self._motion_s,
            "overhead_s": rest,
            "readback_s": self._readback_s,
            "record_s": self._record_s,
            "prepare_wait_s": self._prepare_s,
            "late_restarts": self._late_restarts,
        }

    # ---------------------------------------------------------------- run
    async def run(self) -> ScanOutcome:
        """Pre-flight, run every frame, clean up; returns the outcome (pre-flight refusals raise)."""
        self._task = asyncio.current_task()
        t0 = time.monotonic()
        started = False
        status, reason, pending, interrupted = "complete", "", None, False
        try:
            self._check_abort()
            self.state = "preflight"
            if not self.skip_preflight:
                await self.rig.preflight(self.plan, self.mode, self.frame_rate_hz)
            self._check_abort()
            await self.rig.prepare(self.plan)
            self._check_abort()
            start = ScanStart(
                plan=self.plan,
                axes=dict(self.rig.axes),
                mode=self.mode,
                started_utc=datetime.now(UTC).isoformat(timespec="seconds"),
                sim=self.rig.sim,
                extra=self.start_extra,
            )
            self._notify("on_start", start)
            started = True
            self.state = "running"
            await self._subscribers_ready()
            t0 = time.monotonic()
            with steady_collection():  # no full collection pauses the frames
                if self.mode == "step":
                    await self._run_step(t0)
                else:
                    await self._run_continuous(t0)
        except RefusedError:
            status = "refused"
            raise
        except (KeyboardInterrupt, asyncio.CancelledError) as exc:
            status, reason, pending, interrupted = "aborted", self._why(exc), exc, True
        except Exception as exc:  # a device or recorder error ends the scan safely
            status, reason = "aborted", self._why(exc)
            log.error("scan aborted: %s", reason, exc_info=not is_expected(exc))  # orbitct's own fault: its trace
        finally:
            await self._cleanup(status, interrupted)
            self.state = "aborted" if status == "refused" else status
            if started:
                end = ScanEnd(status, reason, self.n_done, time.monotonic() - t0)
                self._notify("on_finish", end, final=True)
            if status != "refused":
                report(
                    self.progress, "scan", self.n_done, self.plan.n_frames, f"{status}{': ' + reason if reason else ''}"
                )
        if pending is not None:
            raise pending  # Ctrl-C or a cancellation from outside: propagate after cleanup
        return ScanOutcome(status, reason, self.n_done, self.plan.n_frames, time.monotonic() - t0)

    async def _cleanup(self, status: str, interrupted: bool) -> None:
        """Halt every axis (on abort) and switch X-rays off; never raises, never skipped by a second cancel."""

        async def _do() -> None:
            if self._stop_task is not None:
                with contextlib.suppress(BaseException):
                    await self._stop_task
            try:
                if status == "complete":
                    await self.rig.restore()
                else:
                    await self.rig.stop_all(interrupted=interrupted)
            except Exception as exc:  # noqa: BLE001
                log.error("cleanup after scan failed: %s; stopping everything", exc)
                try:
                    await self.rig.stop_all()
                except Exception as exc2:  # noqa: BLE001
                    log.error("stop_all failed too: %s", exc2)

        task = asyncio.ensure_future(_do())
        while not task.done():
            try:
                await asyncio.shield(task)
            except asyncio.CancelledError:
                continue
            except Exception:  # noqa: BLE001
                break

    def _notify(self, method: str, event: Any, final: bool = False) -> None:
        for sub in self.subscribers:
            fn: Callable[[Any], None] | None = getattr(sub, method, None)
            if fn is None:
                continue
            if final:
                try:
                    fn(event)
                except Exception as exc:  # noqa: BLE001
                    log.error("subscriber %r failed in %s: %s", sub, method, exc)
            else:
                fn(event)

    async def _subscribers_ready(self) -> None:
        """Await subscribers that start work of their own (an ``async ready()``) before the first frame; an abort
        meanwhile ends the wait."""
        for sub in self.subscribers:
            ready = getattr(sub, "ready", None)
            if ready is None:
                continue
            task = asyncio.ensure_future(ready())
            try:
                while not task.done():
                    self._check_abort()
                    await asyncio.wait({task}, timeout=0.05)
            finally:
                if not task.done():
                    task.cancel()
            try:
                task.result()
            except Exception as exc:  # a helper that could not start: its own sentence is the reason
                raise AcquireError(str(exc) or "a subscriber of the scan could not start") from exc

    async def _boundary(self) -> None:
        """Frame boundary: honour abort and pause (X-rays stay off while paused)."""
        self._check_abort()
        if not self._resume.is_set():
            self.state = "paused"
            await self.rig.restore()  # X-rays off while paused
            report(self.progress, "scan", self.n_done, self.plan.n_frames, "paused")
            await self._resume.wait()
            self._check_abort()
            self.state = "running"

    # ----------------------------------------------------------- frames
    def _record_motion(self, t_start: float) -> None:
        self._motion_s += time.monotonic() - t_start

    def _true_vector(self, frame: Frame) -> NDArray[np.float64] | None:
        """The view a simulated panel rendered the frame at (simulation truth travels in frame metadata)."""
        tv = frame.meta.get("truth_vectors") if self.rig.sim else None
        return None if tv is None else np.asarray(tv, dtype=float)

    async def _shoot(self, f: FramePlan, t0: float, after_exposure: Callable[[], None] | None = None) -> None:
        """Read back, expose, record one frame with the axes at rest."""
        self._record(await self._expose(f, t0, after_exposure), t0)

    async def _expose(
        self,
        f: FramePlan,
        t0: float,
        after_exposure: Callable[[], None] | None = None,
        *,
        sweeping: bool = False,
        next_exposure_s: float | None = None,
    ) -> FrameRecord:
        """Read back and expose one frame, not yet recorded. ``sweeping``: the axes move through the exposure, so
        they are read back again once it is over and each read-back is interpolated to the exposure's middle (read
        before it only, a sweep at 4 frames/s on the simulated bench recorded the stage 0.5 degrees short of where
        it was)."""
        t_a = time.monotonic()
        encoders = await self.rig.read_positions()
        t_frame = time.monotonic() - t0
        t_b = time.monotonic()
        read_after: asyncio.Future[tuple[float, dict[str, float]]] | None = None

        def exposed() -> None:
            nonlocal read_after
            read_after = asyncio.ensure_future(self._timed_read())
            if after_exposure is not None:
                after_exposure()

        try:
            if sweeping:
                frame = await self.rig.acquire(f.image_key, after_exposure=exposed, next_exposure_s=next_exposure_s)
            elif after_exposure is None:
                frame = await self.rig.acquire(f.image_key)
            else:
                frame = await self.rig.acquire(f.image_key, after_exposure=after_exposure)
            t_c = time.monotonic()
            self._check_abort()  # a frame taken while the abort was halting the rig is not recorded
            if read_after is not None:
                window = self.rig.last_exposure_s() if isinstance(self.rig, SweepRig) else None
                t_after, after = await read_after
                if window is not None:
                    encoders = _interpolated(encoders, 0.5 * (t_a + t_b), after, t_after, 0.5 * sum(window))
                    t_frame = 0.5 * sum(window) - t0  # the frame's time: its exposure's middle, as its read-backs
        finally:
            if read_after is not None and not read_after.done():  # failed or aborted: no read outlives the frame
                read_after.cancel()
                with contextlib.suppress(BaseException):
                    await read_after
        truth = self._true_vector(frame) if f.image_key == ImageKey.PROJECTION else None
        self._acquire_s += t_c - t_b
        self._readback_s += t_b - t_a
        return FrameRecord(
            index=f.index,
            image_key=f.image_key,
            view=f.view,
            time_s=t_frame,
            frame=frame.data,
            commanded=f.targets,
            encoders=encoders,
            nominal_vector=f.nominal_vector,
            true_vector=truth,
        )

    def _record(self, rec: FrameRecord, t0: float) -> None:
        """Hand an exposed frame to the subscribers and report progress (``t0``: when the frames began)."""
        t_r = time.monotonic()
        self._notify("on_frame", rec)
        self.n_done += 1
        t_d = time.monotonic()
        self._record_s += t_d - t_r
        elapsed = t_d - t0
        self._run_s = elapsed
        rate = self.n_done / elapsed if elapsed > 0 else 0.0
        learned = self._pace.seconds_left(self.n_done) if self._pace is not None else None
        left = (
            learned if learned is not None else (self.plan.n_frames - self.n_done) / rate if rate > 0 else float("nan")
        )
        report(self.progress, "scan", self.n_done, self.plan.n_frames, "", rate_fps=rate, time_left_s=left)

    async def _timed_read(self) -> tuple[float, dict[str, float]]:
        """The read-back of every axis and the middle of the time it took (``time.monotonic()``)."""
        t = time.monotonic()
        positions = await self.rig.read_positions()
        return 0.5 * (t + time.monotonic()), positions

    async def _run_step(self, t0: float) -> None:
        """Move, wait on target, settle, expose, read. With ``motion.overlap_readout`` the move to the
        next frame starts once the exposure is over, while the panel is read out and the frame recorded.
        A :class:`PreparingRig` prepares its source during the move to a projection."""
        frames = list(self.plan)
        settle_s = self.motion.settle_ms / 1000.0
        timeout = self.motion.move_timeout_s
        last: dict[str, float] | None = None
        ahead: tuple[dict[str, float], asyncio.Future[None]] | None = None  # move started during readout
        self._pace = pace = ScanPace(frames, self.rig.travel_s, settle_s)
        try:
            for k, f in enumerate(frames):
                await self._boundary()
                cmd = f.targets
                t_m = time.monotonic()
                if cmd != last:
                    prep = self._prepare_during_move() if f.image_key == ImageKey.PROJECTION else None
                    try:
                        arrived = False
                        if ahead is not None:
                            cmd_ahead, move = ahead
                            ahead = None
                            await move
                            arrived = cmd_ahead == cmd
                        if not arrived:
                            await self.rig.move_to(cmd, timeout)
                        if settle_s > 0:
                            await asyncio.sleep(settle_s)
                        self._record_motion(t_m)
                        if prep is not None:
                            self._learn_move(time.monotonic() - t_m)
                            if prep.started:  # under way: let it finish; not yet: the exposure prepares itself
                                t_p = time.monotonic()
                                await prep.task
                                self._prepare_s += time.monotonic() - t_p
                    finally:  # done, failed or aborted: no preparation outlives the move (cancelled: X-rays off)
                        if prep is not None and not prep.task.done():
                            prep.task.cancel()
                            with contextlib.suppress(BaseException):
                                await prep.task
                        elif prep is not None and not prep.task.cancelled():
                            # failed while the move failed or was cancelled (Ctrl-C: the stop drops the source):
                            # the scan's reason is said once; no "Task exception was never retrieved" trace
                            prep.task.exception()
                    last = cmd
                nxt = frames[k + 1] if k + 1 < len(frames) else None
                start_next: Callable[[], None] | None = None
                if (
                    self.motion.overlap_readout
                    and nxt is not None
                    and f.image_key == ImageKey.PROJECTION
                    and nxt.targets != cmd
                ):

                    def start_next(nxt_cmd: dict[str, float] = nxt.targets) -> None:
                        nonlocal ahead
                        ahead = (nxt_cmd, asyncio.ensure_future(self.rig.move_to(nxt_cmd, timeout)))

                t_s = time.monotonic()
                await self._shoot(f, t0, after_exposure=start_next)
                pace.moved(k, t_s - t_m)
                pace.took(k, time.monotonic() - t_s)
                if pace.projections_seen == PROJECTIONS_TIMED and f.image_key == ImageKey.PROJECTION:
                    left = pace.seconds_left(k + 1) or 0.0
                    what = f"acquiring {len(frames)} frames"
                    report_expected(self.progress, what, time.monotonic() - t0 + left, where="rig")
        finally:
            if ahead is not None:  # scan ending early: let the started move end (cleanup halts it anyway)
                done, _ = await asyncio.wait({ahead[1]}, timeout=timeout)
                for move in done:
                    if not move.cancelled():
                        move.exception()

    def _prepare_during_move(self) -> _Preparation | None:
        """Start the source's preparation so that it is ready about when the move to the next projection ends.

        It starts ``prep_s`` before the end the recent moves predict (at once while nothing is known): the
        preparation no longer adds to the frame time, and high voltage is not on long before the exposure.
        """
        if not isinstance(self.rig, PreparingRig):
            return None
        rig: PreparingRig = self.rig
        delay = 0.0 if self._move_s is None else max(0.0, self._move_s - 1.2 * rig.prep_s)

        async def _run() -> None:  # runs once scheduled: ``prep`` is bound by then
            if delay > 0:
                await asyncio.sleep(delay)
            prep.started = True
            await rig.prepare_exposure()

        prep = _Preparation(asyncio.ensure_future(_run()))
        return prep

    def _learn_move(self, seconds: float) -> None:
        """Running estimate of a move to the next projection, settling included (the recent moves weigh most)."""
        self._move_s = seconds if self._move_s is None else 0.7 * self._move_s + 0.3 * seconds
