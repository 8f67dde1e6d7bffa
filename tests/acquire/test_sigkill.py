"""A scan process killed with SIGKILL leaves a readable file with every frame reported as written."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from click.testing import CliRunner

from orbitct.scanfile import ScanFile
from orbitct_app.cli.main import cli

pytestmark = pytest.mark.system

ROOT = Path(__file__).resolve().parents[2]  # the repository: tests.helpers is importable from there


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_sigkill_mid_scan_then_repair(tmp_path: Path) -> None:
    out = tmp_path / "killed.h5"
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from acquire.runner import run_scan
        from tests.helpers.bench import small_request
        def progress(event):
            if event.stage == "scan" and not event.message:
                print(event.done, flush=True)   # reported only after the recorder flushed the frame
        run_scan(small_request({str(out)!r}, frames=200), progress=progress)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout is not None
    reported = 0
    while reported < 12:
        line = proc.stdout.readline()
        assert line, f"scan process ended early (rc={proc.poll()})"
        reported = int(line)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    with ScanFile(out) as sf:  # readable as is, still 'acquiring'
        assert sf.status == "acquiring" and sf.n_frames >= reported
        n_before = sf.n_frames
    result = CliRunner().invoke(cli, ["scan", "repair", str(out)])
    assert result.exit_code == 0, result.output
    with ScanFile(out) as sf:
        assert sf.status == "aborted" and sf.status_reason == "interrupted"
        assert sf.n_frames >= reported and sf.n_frames in (n_before, n_before - 1)
        proj = sf.projection_indices
        assert sf.geometry("nominal")[proj].valid.all()
        assert sf.frames[sf.n_frames - 1].max() > 0


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_ctrl_c_aborts_cleanly(tmp_path: Path) -> None:
    out = tmp_path / "ctrlc.h5"
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from acquire.runner import run_scan
        from tests.helpers.bench import small_request
        def progress(event):
            if event.stage == "scan" and not event.message:
                print(event.done, flush=True)
        res = run_scan(small_request({str(out)!r}, frames=200), progress=progress)
        print("END", res.status, res.reason, flush=True)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout is not None
    while int(proc.stdout.readline()) < 8:
        pass
    os.kill(proc.pid, signal.SIGINT)
    rest = proc.communicate(timeout=60)[0]
    assert proc.returncode == 0 and "END aborted interrupted by the user (Ctrl-C)" in rest
    with ScanFile(out) as sf:
        assert sf.status == "aborted" and sf.status_reason == "interrupted by the user (Ctrl-C)"
