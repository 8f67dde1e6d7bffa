"""A scan file that reads its frames from another (``calibrate --out``): nothing copied, the scan unchanged, and
refused in plain words when the scan it reads from is gone or changed."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from orbitct.scanfile import ScanFile, ScanFileError, write_linked_scan
from tests.orbitct.test_scanfile import _write


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_linked_file_reads_the_scans_frames_and_takes_results_without_touching_the_scan(tmp_path: Path) -> None:
    scan = tmp_path / "scan.h5"
    geom = _write(scan)
    before = _digest(scan)
    linked = write_linked_scan(scan, tmp_path / "out" / "calibrated.h5")
    with ScanFile(linked, "r+") as f, ScanFile(scan) as s:
        assert f.frames_file == scan.resolve() and s.frames_file == scan
        assert f.n_frames == s.n_frames and f.count_by_kind() == s.count_by_kind()
        np.testing.assert_array_equal(f.frames[...], s.frames[...])
        assert f.geometry("nominal")[2:].allclose(geom) and f.marker_diameter_mm == s.marker_diameter_mm
        f.h5.create_dataset("geometry/calibrated/vectors", data=geom.vectors[:1].repeat(7, axis=0))
    assert _digest(scan) == before  # byte for byte
    with h5py.File(linked) as f:
        assert f.attrs["frames_file"] == "../scan.h5" and f["frames/data"].is_virtual
    # a linked file linked again reads from the scan itself, not through the first
    again = write_linked_scan(linked, tmp_path / "again.h5")
    with h5py.File(again) as f:
        assert f.attrs["frames_file"] == "scan.h5"
        assert {s.file_name for s in f["frames/data"].virtual_sources()} == {"scan.h5"}
    with ScanFile(again) as f:
        assert "geometry/calibrated" in f.h5 and f.frames[3].sum() > 0


def test_the_two_files_move_together(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    _write(tmp_path / "a" / "scan.h5")
    write_linked_scan(tmp_path / "a" / "scan.h5", tmp_path / "a" / "out.h5")
    shutil.move(tmp_path / "a", tmp_path / "b")
    with ScanFile(tmp_path / "b" / "out.h5") as f:
        assert f.frames[2].sum() > 0


def test_a_linked_file_whose_scan_is_gone_or_changed_is_refused_with_what_to_do(tmp_path: Path) -> None:
    scan, linked = tmp_path / "scan.h5", tmp_path / "out.h5"
    _write(scan)
    write_linked_scan(scan, linked)
    scan.rename(tmp_path / "moved.h5")
    with pytest.raises(
        ScanFileError, match=r"out.h5: its frames are kept in scan.h5, which is not there; put the scan back"
    ):
        ScanFile(linked)
    _write(scan, n_proj=3)  # another scan under the same name: fewer frames
    with pytest.raises(ScanFileError, match="scan.h5 no longer holds the frames this file reads from it"):
        ScanFile(linked)


def test_virtual_frames_from_a_file_the_scan_does_not_name_are_still_refused(tmp_path: Path) -> None:
    scan, linked = tmp_path / "scan.h5", tmp_path / "out.h5"
    _write(scan)
    write_linked_scan(scan, linked)
    with h5py.File(linked, "r+") as f:
        del f.attrs["frames_file"]
    with pytest.raises(ScanFileError, match="stored in other files"):
        ScanFile(linked)
    with h5py.File(linked, "r+") as f:
        f.attrs["frames_file"] = "other.h5"
    with pytest.raises(ScanFileError, match="/frames/data must map the frames of other.h5"):
        ScanFile(linked)
