"""Pause/resume, abort, cancellation and device faults: every exit path halts axes, X-rays off, valid file."""

from __future__ import annotations

import asyncio
import gc
import time
from typing import Any

import pytest

from acquire.rigs.bench import BenchRig, open_bench
from acquire.runner import ScanRequest, ScanRunner
from devices.errors import DeviceError
from devices.sim import twin_of
from orbitct.progress import ProgressEvent
from orbitct.scanfile import ScanFile
from tests.helpers.bench import small_config

pytestmark = [pytest.mark.timeout(120), pytest.mark.system]


async def _until(pred: Any, timeout_s: float = 30.0) -> None:
    t_end = asyncio.get_running_loop().time() + timeout_s
    while not pred():
        if asyncio.get_running_loop().time() > t_end:
            raise TimeoutError("condition not reached")
        await asyncio.sleep(0.005)


async def _assert_safe(bench: BenchRig) -> None:
    """No axis moving and no X-rays."""
    assert not await bench.hexapod.moving()
    assert not await bench.stage.moving()
    state = await bench.xray.read()
    assert not state["hv_on"] and not state["exposing"] and state["state"] != "EXPOSING"


def _run_with_bench(req: ScanRequest, scenario: Any) -> Any:
    async def main() -> Any:
        cfg = req.resolved_config()
        async with open_bench(cfg, sim=True) as bench:
            events: list[ProgressEvent] = []
            runner = ScanRunner(req, rig=bench, progress=events.append)
            task = asyncio.ensure_future(runner.run())
            out = await scenario(runner, task, bench, events)
            return out

    return asyncio.run(main())


@pytest.mark.parametrize("overlap", [False, True], ids=["strict", "overlapped-readout"])
def test_abort_mid_scan_halts_and_leaves_valid_aborted_file(request_factory, overlap: bool) -> None:
    cfg = small_config()
    cfg = cfg.model_copy(update={"motion": cfg.motion.model_copy(update={"overlap_readout": overlap})})
    req = request_factory(frames=30, config=cfg)

    async def scenario(runner: ScanRunner, task: asyncio.Task, bench: BenchRig, events: list) -> None:
        await _until(lambda: runner._engine is not None and runner._engine.n_done >= 8)
        runner.abort("operator pressed stop")
        res = await task
        assert res.status == "aborted" and res.reason == "operator pressed stop"
        assert 8 <= res.n_frames < res.n_planned
        await _assert_safe(bench)
        assert events[-1].message == "aborted: operator pressed stop"

    _run_with_bench(req, scenario)
    with ScanFile(req.out) as sf:
        assert sf.status == "aborted" and sf.status_reason == "operator pressed stop"
        assert sf.n_frames >= 8 and sf.geometry("nominal").n_views == sf.n_frames


def test_pause_holds_at_a_frame_boundary_and_resume_completes(request_factory) -> None:
    req = request_factory(frames=12)

    async def scenario(runner: ScanRunner, task: asyncio.Task, bench: BenchRig, events: list) -> None:
        await _until(lambda: runner._engine is not None and runner._engine.n_done >= 7)
        runner.pause()
        await _until(lambda: runner.state == "paused")
        held = runner._engine.n_done
        await asyncio.sleep(0.3)
        assert runner._engine.n_done == held and runner.state == "paused"
        xray = await bench.xray.read()
        assert not xray["exposing"] and not xray["hv_on"]  # high voltage off while paused
        assert twin_of(bench.xray).state.name == "IDLE"  # what the generator itself says
        runner.resume()
        res = await task
        assert res.status == "complete" and res.n_frames == res.n_planned
        assert any(e.message == "paused" for e in events)

    _run_with_bench(req, scenario)


def test_cancellation_from_outside_cleans_up_and_propagates(request_factory) -> None:
    req = request_factory(frames=30)

    async def scenario(runner: ScanRunner, task: asyncio.Task, bench: BenchRig, events: list) -> None:
        await _until(lambda: runner._engine is not None and runner._engine.n_done >= 8)
        task.cancel()  # what asyncio.run does on Ctrl-C
        with pytest.raises(asyncio.CancelledError):
            await task
        await _assert_safe(bench)

    _run_with_bench(req, scenario)
    with ScanFile(req.out) as sf:
        assert sf.status == "aborted" and sf.status_reason == "cancelled"


def test_abort_from_another_thread(request_factory) -> None:
    req = request_factory(frames=40)
    runner = ScanRunner(req)
    runner.start()
    t_end = asyncio.get_event_loop_policy().new_event_loop().time() + 60
    import time

    while (runner._engine is None or runner._engine.n_done < 8) and time.monotonic() < t_end:
        time.sleep(0.01)
    runner.abort("emergency stop")
    res = runner.wait(timeout=30)
    assert res.status == "aborted" and res.reason == "emergency stop"
    with ScanFile(req.out) as sf:
        assert sf.status == "aborted"


@pytest.mark.parametrize(
    "fault",
    [
        pytest.param("stuck_axis", marks=pytest.mark.slow),
        "controller_error",
        "interlock",
        "dropped_detector",
        "slow_detector",
    ],
)
def test_device_fault_ends_scan_safely_with_clear_reason(request_factory, fault: str) -> None:
    req = request_factory(f"{fault}.h5", frames=30)
    expected = {
        "stuck_axis": "X",
        "controller_error": "controller error",
        "interlock": "interlock",
        "dropped_detector": "detector",
        "slow_detector": "stall: detector delivered no frame",
    }[fault]

    async def scenario(runner: ScanRunner, task: asyncio.Task, bench: BenchRig, events: list) -> None:
        await _until(lambda: runner._engine is not None and runner._engine.n_done >= 8)
        if fault == "stuck_axis":
            twin_of(bench.hexapod).controller.stick("X")
        elif fault == "controller_error":
            twin_of(bench.stage).faults.add_error(2, "MOV")
        elif fault == "interlock":
            twin_of(bench.xray).set_door(False)
        elif fault == "slow_detector":
            twin_of(bench.detector).readout_s = 25.0  # answers every poll, a frame every 25 s: past stall.frame_s
        else:
            twin_of(bench.detector).drop_connections()
        try:
            res = await asyncio.wait_for(task, 60)
        finally:
            if fault == "stuck_axis":
                twin_of(bench.hexapod).controller.stick("X", False)
                twin_of(bench.hexapod).faults.clear()
            elif fault == "controller_error":
                twin_of(bench.stage).faults.clear()
            elif fault == "interlock":
                twin_of(bench.xray).set_door(True)
        assert res.status == "aborted" and expected.lower() in res.reason.lower(), res.reason
        assert res.n_frames < res.n_planned
        await _assert_safe(bench)

    _run_with_bench(req, scenario)
    with ScanFile(req.out) as sf:
        assert sf.status == "aborted" and expected.lower() in sf.status_reason.lower()


def test_the_source_prepares_during_the_move_not_after_it(request_factory) -> None:
    """Step mode with high voltage off between exposures: the preparation runs while the axes move, so the
    exposure finds the generator ready (a rig that cannot prepare ahead pays the preparation per frame)."""
    cfg = small_config(time_scale=2.0, exposure={"exposure_ms": 2.0, "frame_rate_hz": 8.0, "prep_ms": 400.0})
    prep_s = 0.4 / 2.0  # wall clock; the moves between projections take longer (about 0.3 s: a preparation of
    # 0.3 s made the gap between exposures tie with it, and the generator then sometimes kept high voltage on)

    def acquire_s_per_projection(prepare_ahead: bool) -> tuple[str, float]:
        async def main() -> tuple[str, float]:
            async with open_bench(cfg, sim=True) as bench:
                if not prepare_ahead:
                    bench.prepare_exposure = None  # type: ignore[assignment]  # a rig that cannot
                res = await ScanRunner(request_factory(config=cfg, frames=12), rig=bench).run()
                return res.status, res.timing["acquire_s"] / 12

        return asyncio.run(main())

    status, ahead = acquire_s_per_projection(True)
    assert status == "complete"
    status, after = acquire_s_per_projection(False)
    assert status == "complete"
    assert after - ahead > 0.6 * prep_s, (ahead, after)  # without: each exposure prepares first


def test_a_preparation_failing_while_the_move_fails_is_said_once_without_a_trace(request_factory) -> None:
    """Ctrl-C during a move: the stop drops the source, so the preparation running during the move fails too.
    The scan's reason is said; the preparation's failure is not left for asyncio to print as "Task exception was
    never retrieved" with a traceback (seen in the CLI's output after a Ctrl-C)."""
    unretrieved: list[str] = []

    async def main() -> str:
        asyncio.get_running_loop().set_exception_handler(lambda loop, ctx: unretrieved.append(ctx["message"]))
        async with open_bench(small_config(), sim=True) as bench:
            asked: list[bool] = []

            async def prepare_fails() -> None:
                asked.append(True)
                raise DeviceError("xray: generator returned to IDLE during prepare")

            move_to = bench.move_to

            async def move_fails_after_the_preparation(targets: Any, timeout_s: float) -> None:
                await asyncio.sleep(0.05)  # a preparation started with this move has failed by then
                if asked:
                    raise DeviceError("stage: halted by the stop")
                await move_to(targets, timeout_s)

            bench.prepare_exposure = prepare_fails  # type: ignore[method-assign]
            bench.move_to = move_fails_after_the_preparation  # type: ignore[method-assign]
            res = await ScanRunner(request_factory(frames=8), rig=bench).run()
            return res.reason

    reason = asyncio.run(main())
    gc.collect()  # an unretrieved task exception is reported when the task is collected
    assert "halted by the stop" in reason
    assert not [m for m in unretrieved if "never retrieved" in m], unretrieved


class _SlowToStart:
    """A subscriber whose own work takes a while to start (an ``async ready()``, as a live calibration has)."""

    def __init__(self, ready_after_s: float) -> None:
        self.ready_after_s, self.ready_at, self.first_frame_at, self.loop_free = ready_after_s, None, None, 0

    def on_start(self, start: Any) -> None:
        pass

    async def ready(self) -> None:
        for _ in range(int(self.ready_after_s / 0.01)):
            await asyncio.sleep(0.01)
            self.loop_free += 1  # the scan's loop keeps running meanwhile (heartbeats, stops)
        self.ready_at = time.monotonic()

    def on_frame(self, record: Any) -> None:
        self.first_frame_at = self.first_frame_at or time.monotonic()

    def on_finish(self, end: Any) -> None:
        pass


def test_the_first_frame_waits_for_subscribers_ready_and_a_stop_ends_the_wait(request_factory) -> None:
    slow = _SlowToStart(0.3)
    req = request_factory(frames=6, config=small_config())

    async def main() -> Any:
        async with open_bench(req.resolved_config(), sim=True) as bench:
            return await ScanRunner(req, rig=bench, subscribers=[slow]).run()

    assert asyncio.run(main()).status == "complete"
    assert slow.ready_at is not None and slow.first_frame_at is not None and slow.first_frame_at >= slow.ready_at
    assert slow.loop_free >= 20

    never = _SlowToStart(600.0)

    async def scenario(runner: ScanRunner, task: asyncio.Task, bench: BenchRig, events: list) -> None:
        await asyncio.sleep(0.5)
        runner.abort("operator pressed stop while a subscriber was starting")
        res = await asyncio.wait_for(task, 10)
        assert res.status == "aborted" and res.n_frames == 0 and never.first_frame_at is None
        await _assert_safe(bench)

    async def main_never() -> Any:
        async with open_bench(req.resolved_config(), sim=True) as bench:
            runner = ScanRunner(req, rig=bench, subscribers=[never])
            await scenario(runner, asyncio.ensure_future(runner.run()), bench, [])

    asyncio.run(main_never())
