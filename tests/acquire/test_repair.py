"""``scan repair``: files left 'acquiring' become 'aborted' (interrupted) and keep every complete frame."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from acquire.errors import RepairError
from acquire.repair import repair_scan
from orbitct.geometry import Panel, ViewGeometry
from orbitct.scanfile import ScanFile, ScanWriter
from orbitct_app.cli.main import cli

pytestmark = pytest.mark.system

DET = Panel(16, 16, 1.0, 1.0)
VEC = ViewGeometry.from_carm(0.0, 0.0, 785.0, 1200.0, DET).vectors[0]


def _partial_file(path: Path, n: int) -> None:
    w = ScanWriter(path, DET, axes={"hexapod.X": "mm"})
    for i in range(n):
        w.append(np.full(DET.shape, i), 0, 0.1 * i, nominal_vector=VEC, encoders={"hexapod.X": i})
    w._f.close()  # leave it 'acquiring', as a killed process would


def test_repair_marks_interrupted(tmp_path: Path) -> None:
    p = tmp_path / "s.h5"
    _partial_file(p, 3)
    rep = repair_scan(p)
    assert rep.changed and rep.status_before == "acquiring" and rep.n_frames == 3
    with ScanFile(p) as sf:
        assert sf.status == "aborted" and sf.status_reason == "interrupted" and sf.n_frames == 3
    assert not repair_scan(p).changed  # idempotent


def test_repair_trims_a_half_written_frame(tmp_path: Path) -> None:
    p = tmp_path / "s.h5"
    _partial_file(p, 4)
    with h5py.File(p, "r+") as f:  # a frame whose data got in but whose image key did not
        f["frames/data"].resize(5, axis=0)
        f["frames/time_s"].resize(5, axis=0)
    rep = repair_scan(p)
    assert rep.n_frames == 4 and rep.truncated_from == 5
    with ScanFile(p) as sf:
        assert sf.frames.shape[0] == 4 and sf.axes("encoders")["hexapod.X"].tolist() == [0, 1, 2, 3]


def test_repair_refuses_what_it_cannot_fix(tmp_path: Path) -> None:
    with pytest.raises(RepairError, match="no such file"):
        repair_scan(tmp_path / "nope.h5")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    with pytest.raises(RepairError, match="cannot open as HDF5"):
        repair_scan(junk)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.attrs["format"] = "something.else"
    with pytest.raises(RepairError, match="not an orbitct scan file"):
        repair_scan(other)


def _writer_process(path: Path, body: str) -> subprocess.Popen[str]:
    """Another process that creates the scan file ``path`` (writer ``w``, panel ``det``, view ``vec``), then runs ``body``."""
    script = textwrap.dedent(f"""
        import sys, time, numpy as np
        from orbitct.geometry import Panel, ViewGeometry
        from orbitct.scanfile import ScanWriter
        det = Panel(16, 16, 1.0, 1.0)
        vec = ViewGeometry.from_carm(0.0, 0.0, 785.0, 1200.0, det).vectors[0]
        w = ScanWriter({str(path)!r}, det)
    """) + textwrap.dedent(body)
    return subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)


def test_writer_killed_with_sigkill_leaves_repairable_file(tmp_path: Path) -> None:
    p = tmp_path / "killed.h5"
    proc = _writer_process(
        p,
        """
        i = 0
        while True:
            w.append(np.full(det.shape, i), 0, float(i), nominal_vector=vec)
            print(i, flush=True)
            i += 1
            time.sleep(0.01)
    """,
    )
    reported = -1
    assert proc.stdout is not None
    while reported < 5:
        reported = int(proc.stdout.readline())
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    with ScanFile(p) as sf:
        assert sf.status == "acquiring" and sf.n_frames >= reported + 1
    result = CliRunner().invoke(cli, ["scan", "repair", str(p)])
    assert result.exit_code == 0, result.output
    assert "marked aborted (interrupted)" in result.output
    with ScanFile(p) as sf:
        assert sf.status == "aborted" and sf.status_reason == "interrupted"
        assert sf.n_frames >= reported + 1
        assert [int(sf.frames[i][0, 0]) for i in range(reported + 1)] == list(range(reported + 1))


def test_repair_refuses_a_file_its_acquisition_still_writes(tmp_path: Path) -> None:
    p = tmp_path / "live.h5"
    proc = _writer_process(
        p,
        """
        w.append(np.zeros(det.shape), 0, 0.0, nominal_vector=vec)
        w._f.close()  # as on a file system without HDF5 locks: nothing stops a second opener
        print("written", flush=True)
        time.sleep(60)
    """,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "written"
        result = CliRunner().invoke(cli, ["scan", "repair", str(p)])
        assert result.exit_code == 2 and f"process {proc.pid} on this machine is still writing it" in result.output
        assert "--force" in result.output
        with ScanFile(p) as sf:
            assert sf.status == "acquiring"
        forced = CliRunner().invoke(cli, ["scan", "repair", "--force", str(p)])
        assert forced.exit_code == 0 and "marked aborted" in forced.output
    finally:
        proc.kill()
        proc.wait()


def test_a_file_from_another_machine_counts_as_live_while_it_changes(tmp_path: Path) -> None:
    p = tmp_path / "remote.h5"
    _partial_file(p, 2)
    with h5py.File(p, "r+") as f:
        f["provenance"].attrs["writer_host"] = "bench-pc-elsewhere"
    with pytest.raises(RepairError, match="changed 0 s ago .written on bench-pc-elsewhere."):
        repair_scan(p)
    os.utime(p, (0, 0))  # quiet for long
    assert repair_scan(p).changed
