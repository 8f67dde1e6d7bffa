"""``orbitct scan`` killed by SIGTERM or SIGHUP (systemctl stop, timeout, a closed terminal) still cleans up:
axes halted, X-rays off, the file aborted with the reason. The twins run in this process, so their state can be
read after the command has gone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from devices.xray_registers import GeneratorState
from orbitct.scanfile import ScanFile
from tests.helpers.twin_bench import twin_bench

pytestmark = [pytest.mark.system, pytest.mark.timeout(180)]
ROOT = Path(__file__).resolve().parents[3]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_signal_aborts_the_scan_cleanly(tmp_path: Path, sig: signal.Signals) -> None:
    with twin_bench(f"signals-{sig.name}", time_scale=5.0) as bench:
        bench.reference()
        config = tmp_path / "bench.yaml"
        config.write_text(yaml.safe_dump(bench.config.model_dump(mode="json")))
        out = tmp_path / "scan.h5"
        cmd = [
            sys.executable,
            "-m",
            "orbitct_app.cli.main",
            "scan",
            "--config",
            str(config),
            "--orbit",
            "sawtooth",
            "--frames",
            "300",
            "-p",
            "amplitude_deg=10",
            "--out",
            str(out),
        ]
        proc = subprocess.Popen(
            cmd,
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )
        xray, hexapod, stage = bench.xray.twin, bench.hexapod.twin.controller, bench.stage.twin.controller
        t0 = time.monotonic()
        while xray.frame_counter < 5:  # the scan is exposing projections
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() - t0 < 60, "the scan did not start"
            time.sleep(0.02)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 128 + sig, err
        assert not hexapod.is_moving() and not stage.is_moving()
        assert xray.state not in (GeneratorState.PREP, GeneratorState.READY, GeneratorState.EXPOSING)  # HV off
        assert not xray.prep_req and not xray.expose_req
    with ScanFile(out) as sf:
        assert sf.status == "aborted" and sig.name in sf.status_reason
        assert sf.n_frames >= 4 + 4  # 2 darks and 2 flats, then the projections recorded before the signal
