"""Bad input gives named errors or per-view warnings, never a silent wrong answer; BBs leaving the FOV."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

import calib
from orbitct.scanfile import ScanFile, ScanWriter
from orbitct.verdict import Verdict
from tests.helpers.calib_scans import (
    detector,
    perturbed,
    sawtooth,
    spiral_markers,
    write_scan,
)


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
    truth = ViewGeometry(tv[proj], res.geometry.panel)
    r_px = 0.5 * 3.17 * float(np.median(truth.sdd / truth.sod())) / truth.panel.pitch_row  # the BB's radius
    inside = (tuv[:, 7, 1] - r_px >= 0) & (tuv[:, 7, 1] + r_px <= 255)  # the whole BB on the panel
    seen = np.isfinite(res.uv[proj, k, 0])
    assert 0.1 < inside.mean() < 0.95
    assert not seen[~inside].any()  # a BB cut by the edge is never used
    assert seen[inside].mean() > 0.8
    assert tuv[seen, 7, 1].min() < r_px + 1.5  # found up to the edge
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


def _blank(fov_scan: Path, tmp_path: Path, frames: range) -> Path:
    p = tmp_path / "blank.h5"
    shutil.copyfile(fov_scan, p)
    with h5py.File(p, "r+") as f:
        flat = f["frames/data"][1]
        for i in frames:
            f["frames/data"][i] = flat
    return p


def test_a_short_run_of_views_without_bbs_is_bridged_and_says_so(fov_scan: Path, tmp_path: Path) -> None:
    """Frames 52-56 blanked to the flat field: no BBs there; bridged from frames 51 and 57, with a predicted
    error that grows towards the middle of the gap."""
    bad = list(range(52, 57))
    res = calib.calibrate_scan(_blank(fov_scan, tmp_path, range(52, 57)))
    assert res.unsolved_views == [] and res.geometry.valid[bad].all()
    assert (res.view_status[bad] == 1).all() and (res.view_status[[50, 60]] == 0).all()
    assert any("5 view(s) bridged" in w and "52" in w for w in res.warnings)
    pred = res.predicted_px
    assert pred[54] > pred[52] > pred[50] and pred[54] > pred[56] > pred[60]
    with ScanFile(res.path) as sf:
        assert np.array_equal(sf.h5["geometry/calibrated/view_status"][:], res.view_status)


def test_a_long_run_of_views_without_bbs_fails_loudly(fov_scan: Path, tmp_path: Path) -> None:
    """Frames 40-59 blank: wider than bridge_max_views (10); NaN geometry, and the verdict is failed."""
    bad = list(range(40, 60))
    res = calib.calibrate_scan(_blank(fov_scan, tmp_path, range(40, 60)))
    assert res.unsolved_views == bad
    assert not res.geometry.valid[bad].any() and res.geometry.valid[60]
    assert res.quality is not None and not res.quality.passed
    assert "20 of" in res.quality.reasons[0] and "failed" in res.quality.reasons[0]
    with ScanFile(res.path) as sf:
        attrs = sf.h5["geometry/calibrated"].attrs
        assert attrs["quality"] == "failed" and attrs["n_views_failed"] == 20
        stored = Verdict.from_attrs(attrs)
    assert stored is not None and stored.status == "failed" and stored.reasons == res.quality.reasons


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


@pytest.fixture(scope="module")
def few_bb_scans(tmp_path_factory: pytest.TempPathFactory) -> dict[int, tuple[Path, object]]:
    """256 px, 120 views of 3 and of 4 BBs (no clutter), and their true geometry."""
    root = tmp_path_factory.mktemp("few")
    nominal = sawtooth(120, 256)
    truth = perturbed(nominal, shift_mm=4.0)
    return {
        k: (write_scan(root / f"k{k}.h5", nominal, truth, spiral_markers(k, radius=60.0, height=60.0)), truth)
        for k in (3, 4)
    }


def test_three_bbs_cannot_be_trusted_and_say_so(few_bb_scans: dict[int, tuple[Path, object]], tmp_path: Path) -> None:
    """A pose fitted to 3 BBs fits them exactly whatever their errors: no view can be checked."""
    with pytest.raises(calib.NoMarkersError, match="no view sees the 4 BBs.*at most 3 BBs per view"):
        calib.calibrate_scan(few_bb_scans[3][0], out=tmp_path / "o.h5")


def test_four_bbs_keep_their_correct_detections(few_bb_scans: dict[int, tuple[Path, object]], tmp_path: Path) -> None:
    """With 4 BBs, leaving one out leaves 3 that any pose fits: that rule must not remove correct detections."""
    from calib.evaluate import similarity_aligned_error_px

    path, truth = few_bb_scans[4]
    res = calib.calibrate_scan(path, out=tmp_path / "o.h5")
    proj = np.arange(2, 122)
    seen = np.isfinite(res.uv[proj]).all(-1)
    assert res.n_bbs == 4 and seen.mean() > 0.97
    assert not any("disagree with their view fitted without them" in w for w in res.warnings)
    err, per = similarity_aligned_error_px(res.geometry[proj], truth)
    assert err < 0.3
    # the predicted error is the size of the true one (every view here is observed alike)
    pred = res.predicted_px[proj]
    ok = np.isfinite(pred) & np.isfinite(per)
    assert ok.all() and res.quality is not None and res.quality.passed
    assert 0.5 < np.median(pred) / np.median(per) < 2.0
    assert np.percentile(per, 95) < 3.0 * pred.max()


def test_a_reconstruction_from_a_failed_calibration_is_refused_unless_overridden(
    fov_scan: Path, tmp_path: Path
) -> None:
    """Refused with what to do; asked for anyway, the volume carries the override in its verdict and its file."""
    import recon

    res = calib.calibrate_scan(_blank(fov_scan, tmp_path, range(40, 60)))
    assert res.quality is not None and not res.quality.passed
    small = {"algorithm": "fdk", "geometry": "calibrated", "shape": (8, 16, 16), "voxel_mm": 8.0}
    with pytest.raises(recon.FailedGeometryError, match=r"failed its quality check \(20 of.*; calibrate it again"):
        recon.reconstruct_scan(res.path, **small)
    rr = recon.reconstruct_scan(res.path, **small, accept_failed_geometry=True)
    assert rr.verdict.status == "passed_with_warnings" and rr.params["geometry_override"] is True
    assert "by explicit override" in rr.verdict.warnings[0] and "20 of" in rr.verdict.warnings[0]
    with ScanFile(res.path) as sf:
        _, attrs = sf.read_recon(rr.name)
    assert Verdict.from_attrs(attrs) == rr.verdict
    nominal = recon.reconstruct_scan(res.path, **{**small, "geometry": "nominal"})
    assert nominal.verdict.status == "passed" and nominal.params["geometry_override"] is False
