"""The bluesky orbit plan with a real RunEngine against orbitct's twins on loopback sockets: the documents are
valid, the scan file the callback writes calibrates as ``orbitct scan --sim``'s, and a pause or an abort halts the
axes and switches X-rays off."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import event_model
import numpy as np
import pytest
from bluesky import RunEngine
from bluesky.run_engine import call_in_bluesky_event_loop
from bluesky.utils import RunEngineInterrupted
from click.testing import CliRunner

import calib
from acquire.config import BenchConfig
from acquire.errors import AcquireError
from acquire.options import ScanOptions
from acquire.runner import run_scan
from calib.evaluate import similarity_aligned_error_px
from orbitct.scanfile import ScanFile
from orbitct_app.cli.main import cli
from orbitct_bluesky import Bench, ScanFileCallback, orbit_plan
from orbitct_bluesky.plan import plan_frames
from tests.helpers.bench import SMALL_ERRORS, small_config, small_request

#: the sawtooth ``small_request`` scans (``orbitct scan --sim`` in the tests): 60 frames, small injected errors
SAWTOOTH = ScanOptions(
    orbit="sawtooth",
    orbit_params={"amplitude_deg": 6.0},
    frames=60,
    errors="custom",
    error_params=SMALL_ERRORS,
    seed=1,
)


def validated(documents: list[tuple[str, dict[str, Any]]]) -> Callable[[str, dict[str, Any]], None]:
    """A callback that checks every document against event-model's schemas and keeps it."""

    def check(name: str, doc: dict[str, Any]) -> None:
        event_model.schema_validators[event_model.DocumentNames(name)].validate(doc)
        documents.append((name, doc))

    return check


def aligned_error_px(path: Path, tmp: Path) -> float:
    """Calibrate ``path`` (its quality check passing) and return its error against the simulation truth (px)."""
    result = calib.calibrate_scan(path, out=tmp)
    assert result.quality is not None and result.quality.passed, result.quality
    with ScanFile(path) as sf:
        proj = sf.projection_indices
        truth = sf.geometry("truth")[proj]
    err, _ = similarity_aligned_error_px(result.geometry[proj], truth)
    return float(err)


@pytest.mark.slow
def test_a_sawtooth_run_by_the_run_engine_calibrates_as_orbitct_scan_does(
    RE: RunEngine, open_bench: Callable[[BenchConfig], Bench], tmp_path: Path
) -> None:
    cfg = small_config(size=192)
    bench = open_bench(cfg)
    documents: list[tuple[str, dict[str, Any]]] = []
    recorded = tmp_path / "bluesky.h5"
    RE.subscribe(validated(documents))
    RE.subscribe(ScanFileCallback(recorded))
    RE(orbit_plan(bench, SAWTOOTH))

    names = [n for n, _ in documents]
    assert names[0] == "start" and names[1] == "descriptor" and names[-1] == "stop"
    start, stop = documents[0][1], documents[-1][1]
    assert start["plan_name"] == "orbit_plan" and start["orbitct"]["orbit"]["name"] == "sawtooth"
    assert stop["exit_status"] == "success" and stop["num_events"]["primary"] == names.count("event")
    r = CliRunner().invoke(cli, ["inspect", str(recorded)])
    assert r.exit_code == 0 and "complete" in r.output, r.output

    scanned = tmp_path / "scan.h5"
    req = small_request(scanned, frames=60, config=cfg, errors="custom", error_params=SMALL_ERRORS, seed=1)
    assert run_scan(req).status == "complete"
    with ScanFile(recorded) as a, ScanFile(scanned) as b:
        assert a.n_frames == b.n_frames and a.projection_indices.size == 60
        np.testing.assert_array_equal(a.image_key, b.image_key)
        proj = b.projection_indices
        np.testing.assert_allclose(a.geometry("nominal").vectors[proj], b.geometry("nominal").vectors[proj])
        # the same frames commanded: the same orbit with the same injected errors
        for axis in ("rotation_stage.R", "hexapod.X", "hexapod.U"):
            np.testing.assert_allclose(a.axes("commanded")[axis], b.axes("commanded")[axis])
    by_bluesky = aligned_error_px(recorded, tmp_path / "bluesky-cal.h5")
    by_scan = aligned_error_px(scanned, tmp_path / "scan-cal.h5")
    assert by_bluesky < 1.0 and by_scan < 1.0
    assert by_bluesky <= 1.5 * by_scan + 0.1, (by_bluesky, by_scan)


def _hold_between_exposures(size: int = 32) -> BenchConfig:
    """A bench whose generator keeps high voltage on for a second after each exposure (a 25 s preparation on
    twins 25 times faster than real) when the plan asks it to: a pause must switch it off, not wait for it."""
    return small_config(size=size, exposure={"exposure_ms": 2.0, "frame_rate_hz": 8.0, "prep_ms": 25000.0})


def _interrupt_at(interrupt: Callable[[], Any], n_events: int) -> Callable[[str, dict[str, Any]], None]:
    """A callback that calls ``interrupt`` (the RunEngine's ``request_pause``, ``halt``, ...) once ``n_events``
    frames are recorded, from another thread, as a user's Ctrl-C or a suspender would."""
    seen = {"events": 0}

    def on_document(name: str, doc: dict[str, Any]) -> None:
        if name == "event":
            seen["events"] += 1
            if seen["events"] == n_events:
                threading.Thread(target=interrupt).start()

    return on_document


def _at_rest_and_dark(bench: Bench) -> tuple[bool, bool, dict[str, Any]]:
    async def state() -> tuple[bool, bool, dict[str, Any]]:
        moving = [await bench.stage.driver.moving(), await bench.hexapod.driver.moving()]
        await asyncio.sleep(0.05)
        moving += [await bench.stage.driver.moving(), await bench.hexapod.driver.moving()]
        generator = await bench.xray.driver.read()
        return not any(moving), not generator["hv_on"], generator

    result: tuple[bool, bool, dict[str, Any]] = call_in_bluesky_event_loop(state())
    return result


def _paused_midway(RE: RunEngine, bench: Bench, recorded: Path, options: ScanOptions, n_events: int) -> None:
    """Run ``options``'s orbit, recorded to ``recorded``, until the RunEngine pauses after ``n_events`` frames (the
    generator holding high voltage between exposures); then the axes are at rest and X-rays off."""
    bench.xray.release = False
    RE.subscribe(ScanFileCallback(recorded))
    RE.subscribe(_interrupt_at(RE.request_pause, n_events))
    with pytest.raises(RunEngineInterrupted):
        RE(orbit_plan(bench, options))
    assert RE.state == "paused"
    at_rest, dark, generator = _at_rest_and_dark(bench)
    assert at_rest and dark, generator


@pytest.mark.slow
def test_a_paused_run_halts_and_switches_x_rays_off_then_resumes_to_every_frame(
    RE: RunEngine, open_bench: Callable[[BenchConfig], Bench], tmp_path: Path
) -> None:
    bench, options = open_bench(_hold_between_exposures()), ScanOptions(orbit="sawtooth", frames=24)
    _paused_midway(RE, bench, tmp_path / "paused.h5", options, 12)
    RE.resume()
    assert RE.state == "idle"
    with ScanFile(tmp_path / "paused.h5") as sf:
        assert sf.status == "complete" and sf.projection_indices.size == 24
        assert sf.n_frames == plan_frames(bench, options).n_frames  # darks and flats too: each frame once


@pytest.mark.slow
def test_an_aborted_run_halts_switches_x_rays_off_and_keeps_its_frames(
    RE: RunEngine, open_bench: Callable[[BenchConfig], Bench], tmp_path: Path
) -> None:
    bench, options = open_bench(_hold_between_exposures()), ScanOptions(orbit="sawtooth", frames=24)
    _paused_midway(RE, bench, tmp_path / "aborted.h5", options, 10)
    RE.abort(reason="aborted by the operator")
    at_rest, dark, generator = _at_rest_and_dark(bench)
    assert at_rest and dark, generator
    with ScanFile(tmp_path / "aborted.h5") as sf:
        # bluesky closes a run aborted while paused with no reason in its stop document, only its exit status
        assert sf.status == "aborted" and "exit status abort" in sf.status_reason
        assert 10 <= sf.n_frames < plan_frames(bench, options).n_frames
        assert np.asarray(sf.frames[sf.n_frames - 1]).shape == sf.panel.shape


@pytest.mark.slow
@pytest.mark.parametrize("how", ["halt", "stop"])
def test_a_run_halted_or_stopped_mid_orbit_leaves_the_axes_at_rest_and_x_rays_off(
    RE: RunEngine, open_bench: Callable[[BenchConfig], Bench], tmp_path: Path, how: str
) -> None:
    """``RE.halt()`` (no cleanup by the plan) and ``RE.stop()`` while the run is going on, with high voltage held
    between exposures: the RunEngine stops what the run set, the axes and the generator."""
    bench, options = open_bench(_hold_between_exposures()), ScanOptions(orbit="sawtooth", frames=24)
    bench.xray.release = False
    RE.subscribe(ScanFileCallback(tmp_path / f"{how}.h5"))
    RE.subscribe(_interrupt_at(getattr(RE, how), 10))
    with contextlib.suppress(RunEngineInterrupted):
        RE(orbit_plan(bench, options))
    assert RE.state == "idle"
    at_rest, dark, generator = _at_rest_and_dark(bench)
    assert at_rest and dark, generator
    with ScanFile(tmp_path / f"{how}.h5") as sf:
        assert 10 <= sf.n_frames < plan_frames(bench, options).n_frames


def test_an_infeasible_orbit_is_refused_before_anything_moves(
    RE: RunEngine, open_bench: Callable[[BenchConfig], Bench], tmp_path: Path
) -> None:
    """The pre-flight runs before the run opens: a tilt beyond the hexapod's range moves nothing, writes nothing."""
    bench = open_bench(small_config(size=32))
    targets = [bench.stage.driver.target, bench.hexapod.driver.target]  # where the controllers were last sent
    before = [call_in_bluesky_event_loop(target()) for target in targets]
    documents: list[tuple[str, dict[str, Any]]] = []
    RE.subscribe(validated(documents))
    with pytest.raises(AcquireError, match="nothing moved|workspace|limit"):
        RE(orbit_plan(bench, ScanOptions(orbit="sawtooth", frames=12, orbit_params={"amplitude_deg": 60.0})))
    assert documents == []
    assert [call_in_bluesky_event_loop(target()) for target in targets] == before


def test_continuous_mode_is_refused_with_a_sentence(open_bench: Callable[[BenchConfig], Bench]) -> None:
    bench = open_bench(small_config(size=32))
    with pytest.raises(AcquireError, match="step mode"):
        list(orbit_plan(bench, ScanOptions(mode="continuous")))
