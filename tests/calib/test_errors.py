"""Bad input gives named errors or per-view warnings, never a silent wrong answer; BBs leaving the FOV."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

import calib
from orbitct.scanfile import ScanWriter
from tests.helpers.calib_scans import (
    detector,
    perturbed,
    sawtooth,
    spiral_markers,
    write_scan,
)


@pytest.fixture(scope="module")
def fov_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """256 px, 120 views; BB 8 sits high on the object and leaves the top of the FOV on the upward tilts."""
    nominal = sawtooth(120, 256)
    xyz = np.vstack([spiral_markers(7, radius=60.0, height=60.0), [[0.0, 60.0, 128.0]]])
    return write_scan(tmp_path_factory.mktemp("fov") / "fov.h5", nominal, perturbed(nominal, shift_mm=4.0), xyz)


@pytest.mark.slow
def test_bbs_leaving_the_field_of_view(fov_scan: Path, tmp_path: Path) -> None:
    res = calib.calibrate_scan(fov_scan, out=tmp_path / "o.h5")
    with h5py.File(fov_scan) as f:
        tv = np.asarray(f["truth/geometry/vectors"])
        txyz = np.asarray(f["truth/markers/xyz"])
    from orbitct.geometry import ViewGeometry

    proj = np.flatnonzero(np.isfinite(tv).all(1))
    tuv = ViewGeometry(tv[proj], res.geometry.panel).project(txyz)
    assert res.n_bbs == 8
    k = int(np.argmin(np.abs(res.xyz[:, 2] - res.xyz[:, 2].max())))  # the high BB
    inside = (tuv[:, 7, 1] > 3) & (tuv[:, 7, 1] < 252)
    seen = np.isfinite(res.uv[proj, k, 0])
    assert 0.1 < inside.mean() < 0.95
    assert not seen[~inside].any()
    assert seen[inside].mean() > 0.8
    found = res.uv[proj][seen, k]
    assert np.abs(found - tuv[seen, 7]).max() < 1.0
    assert not res.unsolved_views


def test_no_projections(tmp_path: Path) -> None:
    p = tmp_path / "empty.h5"
    with ScanWriter(p, detector(64)) as w:
        w.append(np.zeros((64, 64)), "dark", 0.0)
        w.append(np.full((64, 64), 1000.0), "flat", 0.0)
    with pytest.raises(calib.NoProjectionsError, match="no projection"):
        calib.calibrate_scan(p)


def test_no_nominal_geometry(fov_scan: Path, tmp_path: Path) -> None:
    p = tmp_path / "nonom.h5"
    shutil.copyfile(fov_scan, p)
    with h5py.File(p, "r+") as f:
        del f["geometry/nominal"]
    with pytest.raises(calib.NoNominalGeometryError):
        calib.calibrate_scan(p)


def test_no_bbs(tmp_path: Path) -> None:
    nominal = sawtooth(20, 96)
    p = write_scan(tmp_path / "nobb.h5", nominal, nominal, np.zeros((0, 3)))
    with pytest.raises(calib.NoMarkersError, match="BB"):
        calib.calibrate_scan(p)


def test_bad_options(fov_scan: Path) -> None:
    with pytest.raises(calib.OptionError, match="method"):
        calib.calibrate_scan(fov_scan, method="magic")
    with pytest.raises(calib.OptionError, match="unknown option"):
        calib.calibrate_scan(fov_scan, colour="red")
    with pytest.raises(calib.OptionError, match="intrinsics"):
        calib.calibrate_scan(fov_scan, intrinsics="everything")


def test_view_with_too_few_bbs_gets_nan_and_a_warning(fov_scan: Path, tmp_path: Path) -> None:
    """Frames 50-54 blanked to the flat field: no BBs there."""
    p = tmp_path / "blank.h5"
    shutil.copyfile(fov_scan, p)
    with h5py.File(p, "r+") as f:
        flat = f["frames/data"][1]
        for i in range(52, 57):
            f["frames/data"][i] = flat
    res = calib.calibrate_scan(p)
    bad = list(range(52, 57))
    assert res.unsolved_views == bad
    assert not res.geometry.valid[bad].any() and res.geometry.valid[60]
    assert any("fewer than 3 BBs" in w for w in res.warnings)


@pytest.mark.slow
def test_manual_seeds_for_the_first_frame_are_accepted(fov_scan: Path, tmp_path: Path) -> None:
    with h5py.File(fov_scan) as f:
        from orbitct.geometry import Panel, ViewGeometry

        tv = np.asarray(f["truth/geometry/vectors"])
        det = Panel(256, 256, 427 / 256, 427 / 256)
        first = int(np.flatnonzero(np.isfinite(tv).all(1))[0])
        seeds = ViewGeometry(tv[first], det).project(np.asarray(f["truth/markers/xyz"]))[0] + 0.6
    res = calib.calibrate_scan(fov_scan, out=tmp_path / "s.h5", seeds_uv=seeds[np.isfinite(seeds).all(1)])
    assert res.n_bbs == 8
    with pytest.raises(calib.OptionError, match="seeds_uv"):
        calib.calibrate_scan(fov_scan, out=tmp_path / "s2.h5", seeds_uv=[1.0, 2.0, 3.0])
