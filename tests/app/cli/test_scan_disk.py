"""``orbitct scan`` onto a small filesystem that really fills up: refused up front with the numbers, or stopped
cleanly before the disk is full, every written frame readable by ``orbitct inspect`` and the file repairable."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from orbitct.scanfile import ScanFile
from orbitct_app.cli.main import cli
from tests.helpers.bench import small_config
from tests.helpers.smallfs import fill, small_filesystem

pytestmark = [pytest.mark.system, pytest.mark.timeout(180)]
ROOT = Path(__file__).resolve().parents[3]
MB = 1 << 20


def _config(tmp_path: Path, reserve_mb: float) -> Path:
    data = small_config().model_dump(mode="json")
    data["geometry"]["detector"] = {"rows": 256, "cols": 256}  # 128 kB per frame
    data["storage"] = {"reserve_mb": reserve_mb}
    p = tmp_path / "bench.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_a_scan_that_cannot_fit_is_refused_before_anything_moves(tmp_path: Path) -> None:
    with small_filesystem(tmp_path / "disk", 8) as disk:
        out = disk / "scan.h5"
        result = CliRunner().invoke(
            cli,
            [
                "scan",
                "--config",
                str(_config(tmp_path, 1.0)),
                "--orbit",
                "circular",
                "--frames",
                "120",
                "--sim",
                "--out",
                str(out),
            ],
        )
        assert result.exit_code == 2, result.output
        assert "not enough disk space" in result.output and "126 frames of 256x256" in result.output
        assert "storage.reserve_mb" in result.output and "nothing moved" in result.output
        assert not out.exists() and "Traceback" not in result.output


def test_a_disk_filling_up_mid_scan_stops_it_cleanly_with_every_frame_kept(tmp_path: Path) -> None:
    with small_filesystem(tmp_path / "disk", 24) as disk:
        out = disk / "scan.h5"
        cmd = [
            sys.executable,
            "-m",
            "orbitct_app.cli.main",
            "scan",
            "--config",
            str(_config(tmp_path, 2.0)),
            "--orbit",
            "circular",
            "--frames",
            "120",
            "--sim",
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
        t0 = time.monotonic()
        while not out.exists() or out.stat().st_size < 4 * MB:  # the file exists and holds some frames
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() - t0 < 90, "the scan did not start"
            time.sleep(0.01)
        filler = fill(disk, leave_bytes=int(1.5 * MB))  # another program takes the space
        _, err = proc.communicate(timeout=90)
        assert proc.returncode == 1, err
        assert "disk nearly full" in err and "frames kept" in err and "Traceback" not in err
        with ScanFile(out) as sf:
            assert sf.status == "aborted" and "disk nearly full" in sf.status_reason
            n = sf.n_frames
            assert 10 <= n < 126
            assert sf.frames[n - 1].max() > 0  # the last frame is there, not a hole
            assert sf.truth_markers_xyz() is not None  # the truth is written at the start
        shown = CliRunner().invoke(cli, ["inspect", str(out)])
        assert shown.exit_code == 0 and "aborted" in shown.output, shown.output
        repaired = CliRunner().invoke(cli, ["scan", "repair", str(out)])
        assert repaired.exit_code == 0, repaired.output
        filler.unlink()
        again = CliRunner().invoke(
            cli,
            [
                "scan",
                "--config",
                str(_config(tmp_path, 2.0)),
                "--orbit",
                "circular",
                "--frames",
                "20",
                "--sim",
                "--out",
                str(disk / "after.h5"),
            ],
        )
        assert again.exit_code == 0, again.output


ENOSPC_WRITER = """
import sys
import numpy as np
from orbitct.geometry import Panel
from orbitct.scanfile import DiskFullError, ScanWriter

w = ScanWriter(sys.argv[1], Panel(256, 256, 1.0, 1.0), min_free_bytes=int(sys.argv[2]))
try:
    for i in range(1000):
        w.append(np.full((256, 256), 100 + i), 0, float(i), nominal_vector=[0, -500, 0, 0, 500, 0, 1, 0, 0, 0, 0, 1])
except DiskFullError as exc:
    print(exc)
w.finish("aborted", "disk full")
"""


@pytest.mark.parametrize("min_free_bytes", [None, 0], ids=["guarded", "real-ENOSPC"])
def test_a_disk_that_fills_up_leaves_a_file_whose_every_counted_frame_has_its_pixels(
    tmp_path: Path, min_free_bytes: int | None
) -> None:
    """The writer stops while the file can still be closed cleanly; and when the space goes anyway (another
    program, or no guard: HDF5's own ENOSPC), readers and repair leave out the frames whose pixels are missing."""
    with small_filesystem(tmp_path / "disk", 8) as disk:
        out = disk / "s.h5"
        guard = str(2 * 256 * 256 * 2 + (1 << 20)) if min_free_bytes is None else "0"
        run = subprocess.run(
            [sys.executable, "-c", ENOSPC_WRITER, str(out), guard], capture_output=True, text=True, timeout=120
        )
        assert "could not be written" in run.stdout or "not written" in run.stdout, run.stdout + run.stderr
        if min_free_bytes is None:  # stopped before HDF5 saw a failed write: a clean exit
            assert run.returncode == 0 and "needed to write it and close the file cleanly" in run.stdout, run.stderr
        fill(disk, leave_bytes=0).unlink()  # nothing else: the space is back
        with ScanFile(out) as sf:
            n = sf.n_frames
            assert 40 <= n < 64 and sf.status in ("aborted", "acquiring")
            assert all(sf.frames[i].min() == 100 + i for i in range(n))  # every counted frame is whole
        repaired = CliRunner().invoke(cli, ["scan", "repair", str(out)])
        assert repaired.exit_code == 0, repaired.output
        shown = CliRunner().invoke(cli, ["inspect", str(out)])
        assert shown.exit_code == 0 and "aborted" in shown.output and "warning" not in shown.output, shown.output
