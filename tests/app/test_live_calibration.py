"""Live calibration on the twins: beside the recorder, geometry in the file at the end, stop on a warning, killed."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

import calib
from acquire.rigs.bench import open_bench
from acquire.runner import ScanRunner
from devices.sim import twin_of
from orbitct.phantoms.experiments import experiment_phantom
from orbitct.scanfile import ScanFile
from orbitct_app.cli.main import cli
from orbitct_app.live_calibration import LiveCalibrationSubscriber
from tests.helpers.bench import small_config, small_request
from tests.helpers.calib_scans import assert_live_geometry_is_offline

pytestmark = [pytest.mark.system, pytest.mark.slow, pytest.mark.timeout(300)]
ROOT = Path(__file__).resolve().parents[2]


def test_a_scan_calibrated_live_has_the_offline_geometry_when_it_ends(tmp_path: Path) -> None:
    """Darks and flats only before the projections: live detection normalises exactly as offline does, so the
    geometry is the same (with darks and flats after the projections too, offline uses them and live cannot)."""
    out = tmp_path / "live.h5"
    cfg = small_config(
        size=192, calibration_frames={"darks_before": 2, "flats_before": 2, "darks_after": 0, "flats_after": 0}
    )
    sub = LiveCalibrationSubscriber(out, cfg.sim.bb_diameter_mm)
    res = asyncio.run(ScanRunner(small_request(out, frames=60, config=cfg), subscribers=[sub]).run())
    assert res.status == "complete" and sub.error is None and sub.result is not None
    assert sub.live is not None and sub.live.last_frame_to_geometry_s is not None
    assert_live_geometry_is_offline(out, tmp_path)


def test_stop_on_a_warning_halts_the_axes_switches_x_rays_off_and_says_why(tmp_path: Path) -> None:
    """A scan that must stop when a view shows fewer BBs than it needs (here: fewer than 99) stops at the next
    frame, through the engine's own path. The plan is long: the live worker runs at a lower priority than the
    acquisition, and on a loaded machine its first warning can come some frames late."""
    out = tmp_path / "stopped.h5"
    cfg = small_config(size=128)
    req = small_request(out, frames=400, config=cfg)
    sub = LiveCalibrationSubscriber(out, cfg.sim.bb_diameter_mm, abort_on=["few_bbs"])
    sub.settings.min_bbs = 99

    async def main() -> Any:
        async with open_bench(cfg, sim=True) as bench:
            res = await ScanRunner(req, rig=bench, subscribers=[sub]).run()
            assert not await bench.hexapod.moving() and not await bench.stage.moving()
            state = await bench.xray.read()
            assert not state["hv_on"] and not state["exposing"]
            return res

    res = asyncio.run(main())
    assert res.status == "aborted" and "live calibration warning (few_bbs)" in res.reason
    assert res.n_frames < res.n_planned
    with ScanFile(out) as sf:
        assert sf.status == "aborted" and "few_bbs" in sf.status_reason
        assert "geometry/calibrated" not in sf.h5  # an aborted scan is not calibrated live


def test_cli_scan_calibrate_live_reports_the_geometry_and_refuses_without_a_bb_size(tmp_path: Path) -> None:
    out = tmp_path / "cli.h5"
    config = tmp_path / "bench.yaml"
    config.write_text(yaml.safe_dump(small_config(size=192).model_dump(mode="json")))
    r = CliRunner().invoke(
        cli,
        [
            "scan",
            "--config",
            str(config),
            "--orbit",
            "sawtooth",
            "--frames",
            "60",
            "--sim",
            "--out",
            str(out),
            "--calibrate",
            "live",
            "-p",
            "amplitude_deg=6",
        ],
    )
    assert r.exit_code in (0, 3), r.output
    assert "calibrated during the scan" in r.output and "geometry written" in r.output
    with ScanFile(out) as sf:
        assert sf.has_geometry("calibrated")
    r = CliRunner().invoke(
        cli, ["scan", "--config", str(config), "--out", str(tmp_path / "x.h5"), "--calibrate", "live"]
    )
    assert r.exit_code == 2 and "--bb-diameter-mm" in r.output
    r = CliRunner().invoke(
        cli, ["scan", "--config", str(config), "--sim", "--out", str(tmp_path / "y.h5"), "--abort-on", "bb_lost"]
    )
    assert r.exit_code == 2 and "--abort-on needs --calibrate live" in r.output


def test_the_cli_offers_to_stop_on_every_warning_but_the_good_news() -> None:
    from orbitct.livewarnings import ABORT_KINDS
    from orbitct_app.cli import scan

    assert scan.ABORT_KINDS == ABORT_KINDS and "object_moved" in ABORT_KINDS and "bb_found" not in ABORT_KINDS
    r = CliRunner().invoke(cli, ["scan", "--help"])
    assert "object_moved" in r.output


def test_a_killed_scan_with_live_calibration_leaves_a_file_that_calibrates_offline(tmp_path: Path) -> None:
    out = tmp_path / "killed.h5"
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from acquire.runner import run_scan
        from orbitct_app.live_calibration import LiveCalibrationSubscriber
        from tests.helpers.bench import small_config, small_request
        if __name__ == "__main__":
            cfg = small_config(size=192)
            def progress(event):
                if event.stage == "scan" and not event.message:
                    print(event.done, flush=True)
            sub = LiveCalibrationSubscriber({str(out)!r}, cfg.sim.bb_diameter_mm)
            run_scan(small_request({str(out)!r}, frames=120, config=cfg), progress=progress, subscribers=[sub])
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout is not None
    reported = 0
    while reported < 45:
        line = proc.stdout.readline()
        assert line, f"scan process ended early (rc={proc.poll()})"
        reported = int(line)
    import psutil

    children = psutil.Process(proc.pid).children(recursive=True)  # the live calibration's worker among them
    assert children
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    _, alive = psutil.wait_procs(children, timeout=15)  # orphaned, the worker notices and ends by itself
    assert not alive, [c.cmdline() for c in alive]
    r = CliRunner().invoke(cli, ["scan", "repair", str(out)])
    assert r.exit_code == 0, r.output
    res = calib.calibrate_scan(out, out=tmp_path / "offline.h5", bridge_max_views=60, max_predicted_px=100.0)
    assert res.n_bbs >= 4 and res.quality is not None and res.quality.counts["own"] > 0


class _NudgeObject:
    """Moves the object (and the BBs on it) on the simulated table once frame ``at`` has been taken: the panel twin
    images it shifted by ``shift_mm`` from then on."""

    def __init__(self, bench: Any, at: int, shift_mm: tuple[float, float, float]) -> None:
        self.twin, self.at, self.shift = twin_of(bench.detector), at, np.asarray(shift_mm, float)
        self.phantom = experiment_phantom(bench.config.sim.phantom, seed=bench.config.sim.seed)

    def on_start(self, start: Any) -> None:
        pass

    def on_frame(self, record: Any) -> None:
        if record.index == self.at:
            from dataclasses import replace

            ph = self.phantom
            moved = replace(
                ph,
                markers_xyz=ph.markers_xyz + self.shift,
                primitives=tuple(replace(p, center=p.center + self.shift) for p in ph.primitives),
            )
            self.twin.set_phantom(moved)

    def on_finish(self, end: Any) -> None:
        pass


def test_an_object_moved_by_2_mm_mid_scan_is_reported_within_a_few_frames(tmp_path: Path) -> None:
    """Each frame's pose is fitted to the BBs while the scan runs (running RPE and predicted error in the progress
    events); the object moved by 2 mm after frame 84 raises one 'object_moved' naming frame 85, a few frames on."""
    out = tmp_path / "moved.h5"
    cfg = small_config(
        size=192, calibration_frames={"darks_before": 2, "flats_before": 2, "darks_after": 0, "flats_after": 0}
    )
    events: list[Any] = []
    sub = LiveCalibrationSubscriber(out, cfg.sim.bb_diameter_mm, progress=events.append)
    at = 84

    async def main() -> Any:
        async with open_bench(cfg, sim=True) as bench:
            nudge = _NudgeObject(bench, at, (0.0, 0.0, -2.0))  # it settles by 2 mm on the stage
            return await ScanRunner(
                small_request(out, frames=130, config=cfg), rig=bench, subscribers=[sub, nudge]
            ).run()

    res = asyncio.run(main())
    assert res.status == "complete" and sub.error is None and sub.live is not None
    moved = [w for w in sub.live.warnings if w.kind == "object_moved"]
    assert len(moved) == 1, [w.message for w in sub.live.warnings]
    assert at + 1 <= moved[0].since_frame <= at + 3 and moved[0].frame <= at + 10, moved[0].message
    live = [e for e in events if e.stage == "live-calibration" and "rpe_mm" in e.metrics]
    assert len(live) > 60
    predicted = np.array([e.metrics["predicted_px"] for e in live])
    rpe = np.array([e.metrics["rpe_mm"] for e in live])
    assert (predicted > 0).all() and np.median(predicted) < 0.5 and np.median(rpe) < 0.5, (predicted, rpe)
    assert "RPE" in live[-1].message and "predicted" in live[-1].message


def test_a_scan_set_to_stop_when_the_object_moves_stops_there_safely(tmp_path: Path) -> None:
    """``abort_on=["object_moved"]``: the object moved by 2 mm after frame 84 stops the scan a few frames on, through
    the engine's own path (axes halted, X-rays off, the file aborted with the warning as its reason). The plan runs
    well past the move: the live worker runs at a lower priority and may be some frames behind."""
    out = tmp_path / "moved-stop.h5"
    cfg = small_config(
        size=192, calibration_frames={"darks_before": 2, "flats_before": 2, "darks_after": 0, "flats_after": 0}
    )
    sub = LiveCalibrationSubscriber(out, cfg.sim.bb_diameter_mm, abort_on=["object_moved"])

    async def main() -> Any:
        async with open_bench(cfg, sim=True) as bench:
            nudge = _NudgeObject(bench, 84, (0.0, 0.0, -2.0))
            res = await ScanRunner(
                small_request(out, frames=200, config=cfg), rig=bench, subscribers=[sub, nudge]
            ).run()
            assert not await bench.hexapod.moving() and not await bench.stage.moving()
            state = await bench.xray.read()
            assert not state["hv_on"] and not state["exposing"]
            return res

    res = asyncio.run(main())
    assert res.status == "aborted" and "live calibration warning (object_moved)" in res.reason, res.reason
    assert res.n_frames < res.n_planned
    assert sub.live is not None
    moved = [w for w in sub.live.warnings if w.kind == "object_moved"]
    assert len(moved) == 1 and 85 <= moved[0].since_frame <= 87, [w.message for w in sub.live.warnings]
    with ScanFile(out) as sf:
        assert sf.status == "aborted" and "object_moved" in sf.status_reason


def _scan_with_live_worker(tmp_path: Path, out: Path, frames: int = 300) -> tuple[subprocess.Popen[str], Any]:
    """``orbitct scan --sim --calibrate live`` in a process of its own, once its live worker follows frames: the
    process and the worker (a psutil process)."""
    import psutil

    config = tmp_path / "bench.yaml"
    config.write_text(yaml.safe_dump(small_config(size=128).model_dump(mode="json")))
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "orbitct_app.cli.main",
            "scan",
            "--config",
            str(config),
            "--sim",
            "--frames",
            str(frames),
            "--out",
            str(out),
            "--calibrate",
            "live",
            "-p",
            "amplitude_deg=6",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        workers = [c for c in psutil.Process(proc.pid).children() if "resource_tracker" not in " ".join(c.cmdline())]
        if (
            workers
        ):  # then frames being written: the worker is ready and follows them (a fixed pause raced a slow start)
            first = out.stat().st_size if out.exists() else None
            while time.monotonic() < deadline and proc.poll() is None:
                size = out.stat().st_size if out.exists() else None
                if first is None:
                    first = size
                elif size is not None and size >= first + 10 * 128 * 128 * 2:  # ten frames of 128 x 128
                    break
                time.sleep(0.1)
            time.sleep(0.5)
            assert proc.poll() is None, proc.communicate()
            return proc, workers[0]
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.1)
    proc.kill()
    raise AssertionError("no live calibration worker appeared")


def test_a_killed_live_worker_leaves_a_complete_scan_that_says_its_geometry_is_missing(tmp_path: Path) -> None:
    out = tmp_path / "killed-worker.h5"
    proc, worker = _scan_with_live_worker(tmp_path, out)
    worker.kill()
    stdout, stderr = proc.communicate(timeout=120)  # the command ends by itself
    assert proc.returncode == 1, (stdout, stderr)
    assert "complete:" in stdout and "no live geometry" in stderr and "killed by signal 9" in stderr, stderr
    assert f"orbitct calibrate {out}" in stderr and "Traceback" not in stderr
    with ScanFile(out) as sf:
        assert sf.status == "complete" and not sf.has_geometry("calibrated")
        assert sf.live_calibration.startswith("missing: the live calibration stopped: its worker process was killed")
    r = CliRunner().invoke(cli, ["inspect", str(out), "--json"])
    assert "missing: the live calibration stopped" in r.output
    r = CliRunner().invoke(cli, ["calibrate", str(out), "--out", str(tmp_path / "offline.h5")])
    assert r.exit_code in (0, 3) and "Traceback" not in r.output, r.output  # the geometry from the file, afterwards


def test_a_hung_live_worker_never_holds_up_the_scan(tmp_path: Path) -> None:
    """A worker alive but answering nothing (stopped): the scan runs on, completes and is recorded; the command gives
    the worker up and says why, by itself."""
    out = tmp_path / "hung-worker.h5"
    proc, worker = _scan_with_live_worker(tmp_path, out)
    worker.suspend()
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 1 and "complete:" in stdout, (stdout, stderr)
    assert "no live geometry (the live calibration stopped: its worker" in stderr, stderr
    assert not worker.is_running() or worker.status() == "zombie"
    with ScanFile(out) as sf:
        assert sf.status == "complete" and sf.live_calibration.startswith("missing:")


def test_sigterm_ends_a_scan_whose_live_worker_hangs(tmp_path: Path) -> None:
    out = tmp_path / "hung-worker-sigterm.h5"
    proc, worker = _scan_with_live_worker(tmp_path, out, frames=600)
    worker.suspend()
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=30)  # the scan aborts cleanly; the hung worker is not waited for
    assert proc.returncode == 128 + signal.SIGTERM, (stdout, stderr)
    assert not worker.is_running() or worker.status() == "zombie"
    with ScanFile(out) as sf:
        assert sf.status == "aborted" and "SIGTERM" in sf.status_reason
