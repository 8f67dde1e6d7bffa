"""End to end on simulated scans of the paper's experiments (small sizes): identity, accuracy, files, CLI."""

from __future__ import annotations

import hashlib
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

import calib
from calib.evaluate import similarity_aligned_error_px
from orbitct.progress import ProgressEvent
from orbitct.scanfile import ScanFile
from tests.helpers.measured import below

pytestmark = pytest.mark.slow


def _truth(path: Path) -> tuple[np.ndarray, np.ndarray, object]:
    with ScanFile(path) as sf:
        proj = sf.projection_indices
        truth = sf.geometry("truth")
        return proj, truth.project(sf.truth_markers_xyz()), truth


def _identity(uv: np.ndarray, truth_uv: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Truth index of each found BB, the worst purity, and the largest distance of a kept detection."""
    d = np.linalg.norm(uv[:, :, None] - truth_uv[:, None], axis=-1)  # (N, K, Kt)
    seen = np.isfinite(uv[..., 0])
    owner, purity, worst = [], 1.0, 0.0
    for k in range(uv.shape[1]):
        dk = d[seen[:, k], k]
        votes = np.bincount(dk.argmin(1), minlength=truth_uv.shape[1])
        owner.append(int(votes.argmax()))
        purity = min(purity, votes.max() / votes.sum())
        worst = max(worst, float(dk[:, owner[-1]].max()))
    return np.array(owner), purity, worst


@pytest.mark.parametrize("experiment, n_bbs", [("A", 8), ("B", 16)])
def test_every_bb_found_once_with_its_identity(
    simulated_scan: Callable[..., Path], tmp_path: Path, experiment: str, n_bbs: int
) -> None:
    scan = simulated_scan(experiment)
    res = calib.calibrate_scan(scan, out=tmp_path / "out.h5")
    proj, truth_uv, truth = _truth(scan)
    owner, purity, worst = _identity(res.uv[proj], truth_uv[proj])
    assert res.n_bbs == n_bbs
    assert sorted(owner.tolist()) == list(range(n_bbs))
    assert purity == 1.0
    below("worst_detection_px", worst, 2.0)  # no wrong blob: every kept detection is near its own BB
    assert np.isfinite(res.uv[proj]).all(-1).mean() > 0.85
    # 192 px: a BB spans 2.2 px and its centroids scatter ~0.4 px RMS among the clutter (4x the 768 px
    # benchmark scale, where the bound is 0.15 px); 0.45 px here is the same accuracy relative to the noise.
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj])
    below("aligned_error_px", err, 0.45)
    assert res.iterations[-1].rpe_mean_mm < 0.1 * res.iterations[0].rpe_mean_mm


def test_metal_and_small_bbs_are_nan_rather_than_wrong(simulated_scan: Callable[..., Path], tmp_path: Path) -> None:
    scan = simulated_scan("C", 384, 120)  # 2 mm BBs need 384 px to span 2.7 px
    res = calib.calibrate_scan(scan, out=tmp_path / "c.h5")
    proj, truth_uv, truth = _truth(scan)
    owner, purity, worst = _identity(res.uv[proj], truth_uv[proj])
    assert res.n_bbs == 10 and sorted(owner.tolist()) == list(range(10))
    assert purity == 1.0
    below("worst_detection_px", worst, 2.0)
    seen = np.isfinite(res.uv[proj]).all(-1)
    assert 0.6 < seen.mean() < 0.99  # some BBs hidden by screws, spine or each other are left out
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj])
    below("aligned_error_px", err, 0.3)


def test_paper_method_converges_in_two_iterations(simulated_scan: Callable[..., Path], tmp_path: Path) -> None:
    res = calib.calibrate_scan(simulated_scan("A"), method="paper", out=tmp_path / "p.h5", iterations=3)
    m = [s.rpe_mean_mm for s in res.iterations]
    assert len(m) == 4
    assert m[1] < 0.2 * m[0]
    assert m[1] - m[2] < 0.25 * m[1]
    assert abs(m[2] - m[3]) < 0.05 * m[2]


def test_results_written_as_scan_file_says(simulated_scan: Callable[..., Path], tmp_path: Path) -> None:
    src = simulated_scan("A")
    before, digest = src.stat().st_mtime_ns, hashlib.sha256(src.read_bytes()).hexdigest()
    out = tmp_path / "copy.h5"
    res = calib.calibrate_scan(src, out=out, report_dir=tmp_path / "rep")
    assert src.stat().st_mtime_ns == before and hashlib.sha256(src.read_bytes()).hexdigest() == digest
    with h5py.File(src) as f:
        assert "geometry/calibrated" not in f
    # the results file reads the frames from the scan: none copied
    assert out.stat().st_size < src.stat().st_size / 4, (out.stat().st_size, src.stat().st_size)
    with h5py.File(out) as f:
        assert f["frames/data"].is_virtual and f.attrs["frames_file"] == str(Path(os.path.relpath(src, tmp_path)))
    with ScanFile(out) as sf:
        n = sf.n_frames
        g = sf.geometry("calibrated")
        assert g.n_views == n and not g.valid[sf.image_key != 0].any()
        m = sf.markers()
        assert m["uv"].shape == (n, res.n_bbs, 2) and m["xyz"].shape == (res.n_bbs, 3)
        assert np.isnan(m["rpe_mm"][sf.image_key != 0]).all()
        attrs = dict(sf.h5["geometry/calibrated"].attrs)
        for key in ("method", "iterations", "elapsed_s", "rpe_mean_mm", "rpe_median_mm", "rpe_std_mm", "reproj_rms_px"):
            assert key in attrs
        assert attrs["rpe_mean_mm"] == pytest.approx(np.nanmean(m["rpe_mm"]))
        mats = np.asarray(sf.h5["geometry/calibrated/matrices"])
        assert np.allclose(mats[sf.projection_indices], g.matrices[sf.projection_indices])
    for name in ("table1.md", "table1.csv", "rpe_violin.png", "corrections.png", "worst_view.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 0
    # a simulated scan: the corrections plot overlays the truth, in the calibrated frame; across each
    # view's beam they agree (along it a shift only changes magnification and the BBs barely see it)
    truth = res.true_corrections
    assert truth is not None
    proj = np.flatnonzero(np.isfinite(res.corrections["shift_mm"][:, 0]))
    beam = res.nominal.D[proj] - res.nominal.S[proj]
    beam /= np.linalg.norm(beam, axis=1, keepdims=True)
    diff = res.corrections["shift_mm"][proj] - truth["shift_mm"][proj]
    across = diff - (diff * beam).sum(1, keepdims=True) * beam
    spread = np.std(truth["shift_mm"][proj], axis=0).max()
    assert spread > 1.0  # the simulated errors are there to be found
    assert np.sqrt(np.mean((across**2).sum(1))) < 0.1 * spread


def test_cli_calibrates_in_place_and_reports(simulated_scan: Callable[..., Path], tmp_path: Path) -> None:
    from orbitct_app.cli.main import cli

    scan = tmp_path / "a.h5"
    shutil.copyfile(simulated_scan("A"), scan)
    r = CliRunner().invoke(cli, ["calibrate", str(scan), "--method", "paper", "--report", str(tmp_path / "r")])
    assert r.exit_code == 0, r.output
    assert "8 BBs" in r.output and "RPE mean" in r.output
    assert "time: detection " in r.output and " + identification " in r.output and "; writing " in r.output
    assert r.output.index("calibration takes about ") < r.output.index("RPE mean")  # said before it ends
    with ScanFile(scan) as sf:
        assert sf.h5["geometry/calibrated"].attrs["method"] == "paper"
    r = CliRunner().invoke(cli, ["calibrate", str(scan), "--method", "magic"])
    assert r.exit_code != 0


def test_the_predicted_error_tracks_the_true_one_and_fails_the_poor_views(
    simulated_scan: Callable[..., Path], tmp_path: Path
) -> None:
    """96 views at 192 px: a few views see only 4 BBs in a poor layout, or are bridged; the prediction says
    which, the verdict fails on them (max_predicted_px 0.5), and they are the truly poor ones."""
    scan = simulated_scan("A", 192, 96)
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    proj, _, truth = _truth(scan)
    _, per = similarity_aligned_error_px(res.geometry[proj], truth[proj])
    pred = res.predicted_px[proj]
    ok = np.isfinite(pred) & np.isfinite(per)
    assert np.corrcoef(pred[ok], per[ok])[0, 1] > 0.5
    assert 0.5 < np.median(pred[ok]) / np.median(per[ok]) < 2.0
    assert res.quality is not None and not res.quality.passed
    flagged = ok & (pred > 0.5)
    assert flagged.any() and per[flagged].min() > 2.0 * np.median(per[ok])
    assert "max_predicted_px" in res.quality.reasons[-1]


def test_detections_over_rough_background_weigh_less_and_the_views_come_out_closer(
    simulated_scan: Callable[..., Path], tmp_path: Path
) -> None:
    """Experiment A at 512 px: its BBs cross the object's outline twice a turn and sit over clutter, where the
    centroids are off by 2-3 times the typical error. Weighting each detection by its background's RMS
    (``weigh_detections``, the default) calibrates the views measurably closer than weighting all alike."""
    scan = simulated_scan("A", 512, 120)
    proj, _, truth = _truth(scan)
    errors = {}
    for weigh in (False, True):
        res = calib.calibrate_scan(scan, out=tmp_path / f"{weigh}.h5", weigh_detections=weigh)
        assert res.quality is not None and res.quality.passed
        errors[weigh] = similarity_aligned_error_px(res.geometry[proj], truth[proj])[0]
    assert errors[True] < 0.9 * errors[False]


def test_three_times_the_bench_errors_are_recovered_by_tracking_with_larger_jumps(tmp_path: Path) -> None:
    """Errors three times the published bench profile: the BBs are lost with the expected 3 mm jitter; tracking
    again with larger allowed jumps recovers them, the calibration reaches the accuracy of the 1x case, and says so.
    (Twice the profile no longer needs it: its rough solves hold the BB centres; 0.154 px with 3 mm.)"""
    from orbitct.errorprofiles import make_profile
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "x3.h5"
    simulate_scan(
        "A",
        out=scan,
        n_frames=250,
        detector_px=256,
        seed=1,
        overwrite=True,
        errors=make_profile("bench", 1, angle_scale=3 * 250 / 500, shift_amplitude_mm=24.0, shift_noise_mm=6.0),
    )
    first = calib.calibrate_scan(scan, out=tmp_path / "no.h5", recover=False)
    assert first.quality is not None and not first.quality.passed
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    proj, _, truth = _truth(scan)
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj])
    assert res.quality is not None and res.quality.passed and res.quality.counts["own"] == proj.size
    below("aligned_error_px", err, 0.3)
    assert any("allowing" in w and "mm jumps" in w for w in res.warnings)


def test_eight_times_the_bench_errors_calibrate_where_the_jumped_views_are_placed(tmp_path: Path) -> None:
    """Errors eight times the bench profile (about 8 deg and 80 mm: frames jump up to 45 px, farther than the BBs
    lie apart; the robustness sweep's seed 2): the BBs are followed only with 40 or 60 mm jumps allowed, and the views a
    neighbour's pose puts no BB on are placed by a 2-D shift or similarity. Every view is calibrated from its own
    BBs, at the floor, each BB keeping its identity, and the warnings say so."""
    from orbitct.errorprofiles import make_profile
    from orbitct.phantoms.experiments import experiment_phantom
    from orbitct.reference_bench import reference_panel
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "x8.h5"
    simulate_scan(
        experiment_phantom("A", 2),
        out=scan,
        n_frames=250,
        detector_px=384,
        pitch_mm=reference_panel(384).pitch_col,
        seed=2,
        overwrite=True,
        errors=make_profile("bench", 2, angle_scale=8 * 250 / 500, shift_amplitude_mm=64.0, shift_noise_mm=16.0),
    )
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    proj, truth_uv, truth = _truth(scan)
    owner, purity, _ = _identity(res.uv[proj], truth_uv[proj])
    assert res.n_bbs >= 7 and len(set(owner.tolist())) == res.n_bbs and purity == 1.0
    assert res.quality is not None and res.quality.passed and res.quality.counts["own"] == proj.size
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj], max_views=proj.size)
    below("aligned_error_px", err, 0.25)
    assert any("allowing 40 mm jumps" in w or "allowing 60 mm jumps" in w for w in res.warnings)
    assert any("were placed by the 2-D" in w for w in res.warnings)


@pytest.mark.parametrize("bb_search", ["full", "predicted"])
def test_four_times_the_bench_errors_calibrate_to_the_floor(tmp_path: Path, bb_search: str) -> None:
    """Errors four times the bench profile (about 4 deg and 40 mm; frames jump farther than the BBs lie apart):
    every BB keeps its identity, every view is calibrated from its own BBs, as accurately as at 1x. With the
    predicted search one view kept 3 BBs: its neighbours' poses, a jump away, placed none of its others (frame 219
    bridged at 1.0 px predicted); its pose fitted to its own 3 BBs places all 8."""
    from orbitct.errorprofiles import make_profile
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "x4.h5"
    simulate_scan(
        "A",
        out=scan,
        n_frames=250,
        detector_px=256,
        seed=1,
        overwrite=True,
        errors=make_profile("bench", 1, angle_scale=4 * 250 / 500, shift_amplitude_mm=32.0, shift_noise_mm=8.0),
    )
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5", bb_search=bb_search)
    proj, truth_uv, truth = _truth(scan)
    owner, purity, worst = _identity(res.uv[proj], truth_uv[proj])
    assert res.n_bbs == 8 and sorted(owner.tolist()) == list(range(8)) and purity == 1.0
    below("worst_detection_px", worst, 1.0)
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj])
    assert res.quality is not None and res.quality.passed and res.quality.counts["own"] == proj.size
    below("aligned_error_px", err, 0.3)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_torso_seen_from_the_side_keeps_its_bbs_and_no_view_passes_wrong(tmp_path: Path, seed: int) -> None:
    """Experiment C (a torso with a spine and screws, 2 mm BBs) at 512 px: in the lateral views the anatomy gives
    more strong peaks than a fixed 128 candidates hold, and half the BBs were lost (the check failed); with the
    views left with four BBs, two wrong blobs among them fitted a wrong pose closely: seed 0 passed with a view
    22 px off (at 512 candidates), seed 1 with one 7.6 px off. Now both pass, and every view is within 1 px."""
    from orbitct.errorprofiles import make_profile
    from orbitct.phantoms.experiments import experiment_phantom
    from orbitct.simulator import resolve_orbit
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "c.h5"
    simulate_scan(
        experiment_phantom("C"),
        resolve_orbit("C", None, 206),
        out=scan,
        detector_px=512,
        seed=seed,
        errors=make_profile("bench", seed, angle_scale=206 / 500),
    )
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    proj, _, truth = _truth(scan)
    err, per = similarity_aligned_error_px(res.geometry[proj], truth[proj], max_views=proj.size)
    assert res.quality is not None and res.quality.passed, res.quality.reasons
    assert res.quality.counts["own"] >= 0.97 * proj.size
    below("aligned_error_px", err, 0.2)
    below("worst_view_px", np.nanmax(per), 1.0)


#: BBs taped on experiment C's torso (mm) where a calibration passed with views far off (512 px, by seed): a plan of
#: ten whose two jumped frames were identified as six BBs of their own, an island 17-30 px off (3); BBs at random
#: where a jumped frame kept four blobs, two of them wrong, and calibrated 5.8 px off (219), or 7 px off with a
#: bridged neighbour (214); twelve at random whose tracks all broke at one frame, the second half identified as
#: twelve BBs of its own and calibrated 8-22 px off (212)
_C_PLACEMENTS = {
    3: [
        [120.05948988962109, -11.329020439182212, 69.9011687431861],
        [-0.568691102489449, -90.99899561689885, -50.383932249053125],
        [-99.93146517168375, -51.324284764441856, 66.97319974328602],
        [4.089940431635846, 90.9480360244122, -63.33477621143817],
        [-43.104611905287214, -85.0338161113777, 47.983826953567245],
        [-61.87132405170951, 78.2112428655921, -47.152945229141025],
        [116.92110625361391, 23.438137355792644, -57.24749483138615],
        [41.28503473087094, 85.54269412145524, -35.84735122257413],
        [-91.05199954560604, -59.94571816613904, -49.28421149782866],
        [-41.78662005647902, 85.40490781955016, 66.02006658144748],
    ],
    219: [
        [40.56788174868866, 85.73643051786001, -27.192979658104775],
        [-110.82299617749739, -36.54268266287364, -19.745252375386706],
        [-110.90203239566522, -36.4067362752743, -48.12021517965556],
        [120.0496473205991, -11.387912433446246, -68.83328587634298],
        [119.7772495265129, -12.909931606538908, 49.51049868208504],
        [-103.1825622480541, -47.545592775716145, 30.387991841572983],
        [6.7233315923444295, -90.85950875251498, 35.30797970052946],
        [-39.17958874046033, -86.10063731363024, -29.676111343691773],
        [81.0809801955325, 67.5589909353319, -11.565044624672502],
        [-96.76393191860478, -54.65023535146976, -45.34563801618989],
    ],
    212: [
        [-51.01639138203747, -82.52140104859996, -12.230972193847691],
        [109.24919156563205, 39.132678544073926, 60.85516666870416],
        [88.12660071045524, -62.36959995665912, 30.97540478583811],
        [-1.7877690361224607, -90.9900736247822, 34.52483602856991],
        [-50.702208840933935, -82.63079644449489, 42.60777389357183],
        [-120.07666678304292, 11.225492455564197, 46.85942695845273],
        [30.13257653935441, -88.13501806940647, 25.581506835820505],
        [54.76783838974461, -81.15066533697157, 69.31141195678842],
        [-26.872581238917924, 88.72894515758708, 40.717218737044476],
        [9.875463040022524, 90.69662127564342, 45.85780969782799],
        [120.33797999161297, -9.510385187369165, 46.34437572780264],
        [-120.44087851059295, 8.74195672738742, -63.50035733897916],
    ],
    214: [
        [0.724460384152773, 90.99837003863811, 56.662425791815124],
        [115.97326798325541, 25.9671426906386, -24.621512557739543],
        [-105.97928607450687, -43.92725099496318, -9.559369900178744],
        [-120.33038344610141, -9.564643160234713, 11.777055587748606],
        [120.99321769173613, 0.9639243038402808, -13.684461356519932],
        [75.58608727235583, 71.07069803334495, -65.59871290530799],
        [118.46883642755381, -18.523641850010016, -4.2270289574071],
        [1.0904138217477841, -90.99630737118731, 23.27075921443806],
    ],
}


@pytest.mark.parametrize("seed", sorted(_C_PLACEMENTS))
def test_jumped_frames_on_a_torso_do_not_pass_wrong(tmp_path: Path, seed: int) -> None:
    """Frames where the bench jumped: no view may pass far off (a BB seen in a few frames only is left out; a view
    left with four BBs where the views around it see more is assigned again through them; BBs identified twice, in
    two parts of the orbit, are made one)."""
    from orbitct.errorprofiles import make_profile
    from orbitct.phantoms.experiments import experiment_phantom
    from orbitct.simulator import resolve_orbit
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "c.h5"
    phantom = experiment_phantom("C").with_markers(np.array(_C_PLACEMENTS[seed]))
    simulate_scan(
        phantom,
        resolve_orbit("C", None, 206),
        out=scan,
        detector_px=512,
        seed=seed,
        errors=make_profile("bench", seed, angle_scale=206 / 500),
    )
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    proj, _, truth = _truth(scan)
    err, per = similarity_aligned_error_px(res.geometry[proj], truth[proj], max_views=proj.size)
    assert res.quality is not None and res.quality.passed, res.quality.reasons
    below("aligned_error_px", err, 0.2)
    below("worst_view_px", np.nanmax(per), 1.0)


#: ten BBs planned on C's torso for 206 views at 512 px (``calib.plan.plan_placement`` with the phantom's background,
#: seed 0), up to 100 mm from its middle
_C_PLANNED = [
    [-68.2585129615815, 75.14687103558538, 49.34975071862464],
    [100.16704431447579, 51.06381910867867, 88.62180167883189],
    [-59.825749701869775, -79.1059081278152, 69.81830034070651],
    [95.3249581105242, -56.06256559658245, 86.39914647224208],
    [-40.96413419783178, -85.62985830330678, 90.38785483478065],
    [26.07199998817345, 88.8638536420026, -89.64537907451404],
    [52.35681224503901, 82.04539670893742, 99.04169637145083],
    [-79.42580443200987, 68.661910647414, -99.85591695207067],
    [9.246575094059175, -90.73408535195676, -97.60891958458329],
    [120.33873424902693, -9.504980847525989, -99.38718960823294],
]


def _c_scan(tmp_path: Path) -> Path:
    """C's orbit (206 views at 512 px, bench errors) with the ten planned BBs."""
    from orbitct.errorprofiles import make_profile
    from orbitct.phantoms.experiments import experiment_phantom
    from orbitct.simulator import resolve_orbit
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "c.h5"
    simulate_scan(
        experiment_phantom("C").with_markers(np.array(_C_PLANNED)),
        resolve_orbit("C", None, 206),
        out=scan,
        detector_px=512,
        seed=0,
        errors=make_profile("bench", 0, angle_scale=206 / 500),
    )
    return scan


def test_the_ten_planned_bbs_on_c_are_identified_at_the_orbits_own_jitter(tmp_path: Path) -> None:
    """Every BB in nine views of ten, at the floor, without allowing larger jumps than the orbit's: the rough solves
    that tie C's three arcs together hold each BB centre softly to its first triangulation (before, a few centres
    ran off to 1e17 mm, along paths that depended on the CPU's linear algebra, and the BBs were followed only with
    8 or 15 mm jumps, or identified twice)."""
    scan = _c_scan(tmp_path)
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    assert not any("jumps" in w or "identified twice" in w for w in res.warnings), res.warnings
    proj, _, truth = _truth(scan)
    seen = np.isfinite(res.uv[proj]).all(-1).mean(0)
    assert res.uv.shape[1] == 10 and seen.min() >= 0.9, seen
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj], max_views=proj.size)
    assert res.quality is not None and res.quality.passed
    below("aligned_error_px", err, 0.06)


def test_bbs_one_part_of_the_orbit_missed_are_found_through_the_merged_geometry(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tracking broken for every BB where C's orbit jumps to its third arc (done here to the identification's
    answer): six BBs identified in both parts, each twice, and four in the first part only. The twins are made one,
    and the four are then found in the second part's views through the merged geometry (before, they were left out
    of 92 of the 206 views, and those views calibrated from six BBs)."""
    import calib.pipeline

    scan = _c_scan(tmp_path)
    with ScanFile(scan) as sf:
        source = sf.geometry("nominal")[sf.projection_indices].S
    d = source / np.linalg.norm(source, axis=1, keepdims=True)
    jump = int(np.argmax(np.linalg.norm(np.diff(d, axis=0), axis=1))) + 1  # the first view of the third arc
    identified = calib.pipeline.identify

    def broken_at_the_jump(*args, **kwargs):  # type: ignore[no-untyped-def]
        uv, warnings = identified(*args, **kwargs)
        first, second = uv.copy(), uv.copy()
        first[jump:], second[:jump] = np.nan, np.nan
        return np.concatenate([first, second[:, :6]], axis=1), warnings

    monkeypatch.setattr(calib.pipeline, "identify", broken_at_the_jump)
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5", recover=False)
    assert any("identified twice" in w for w in res.warnings), res.warnings
    proj, _, truth = _truth(scan)
    seen = np.isfinite(res.uv[proj]).all(-1).mean(0)
    assert res.uv.shape[1] == 10 and seen.min() >= 0.9, seen
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj], max_views=proj.size)
    assert res.quality is not None and res.quality.passed
    below("aligned_error_px", err, 0.06)


def test_a_panel_with_dead_columns_keeps_the_bbs_they_cross(tmp_path: Path) -> None:
    """Experiment C's 2 mm BBs on a 384-px panel with two dead columns: unfilled, the columns cost half the BBs (5 of
    10 found); filled, 9 (the clean panel: 10, 93 % of the views from their own BBs)."""
    from orbitct.simulator import DetectorModel, simulate_scan

    scan = tmp_path / "dead.h5"
    simulate_scan("C", out=scan, n_frames=250, detector_px=384, detector=DetectorModel(dead_columns=2))
    res = calib.calibrate_scan(scan, out=tmp_path / "cal.h5")
    assert res.xyz.shape[0] >= 9 and (res.view_status[res.view_status >= 0] == 0).mean() > 0.7


def test_a_truncating_panel_uses_bbs_up_to_its_edge_and_flags_what_it_cannot_see(tmp_path: Path) -> None:
    """A 384 px panel with the native 768-px pitch sees half the field: BBs enter and leave all the time.
    Views with four or more whole BBs are calibrated from them (BBs detected up to the panel's edge); the
    others are bridged, and any view whose geometry is off by more than 1 px is flagged by its prediction."""
    from orbitct.errorprofiles import make_profile
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "cut.h5"
    simulate_scan(
        "A",
        out=scan,
        n_frames=120,
        detector_px=384,
        pitch_mm=427.0 / 768,
        seed=0,
        overwrite=True,
        errors=make_profile("bench", 0, angle_scale=120 / 500),
    )
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    proj, truth_uv, truth = _truth(scan)
    g = truth[proj]
    r_px = 0.5 * 3.17 * float(np.median(g.sdd / g.sod())) / g.panel.pitch_row
    whole = ((truth_uv[proj] - r_px - 1 >= 0) & (truth_uv[proj] + r_px + 1 <= 383)).all(-1)
    four = whole.sum(1) >= 4
    status = res.view_status[proj]
    assert (status[four] == 0).mean() >= 0.9
    uv = res.uv[proj]
    edge_px = np.nanmin(np.minimum(uv, 383 - uv))
    assert edge_px < r_px + 2.0  # some BB used with its disc touching the edge zone
    _, per = similarity_aligned_error_px(res.geometry[proj], g)
    off = np.isfinite(per) & (per > 1.0)
    assert (res.predicted_px[proj][off] > 0.5).all()
    assert off.any() and res.quality is not None and not res.quality.passed  # and the verdict says so


def test_timings_leave_compiling_out_once_and_are_never_negative(
    simulated_scan: Callable[..., Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Kernels compiled during identification (the first calibration after installation) were taken off the
    estimation time twice, which then read negative."""
    import calib.pipeline
    from tests.helpers.compiling import compiling_first

    monkeypatch.setattr(calib.pipeline, "identify", compiling_first(calib.pipeline.identify))
    events: list[ProgressEvent] = []
    res = calib.calibrate_scan(simulated_scan("A"), out=tmp_path / "t.h5", progress=events.append)
    said = [e for e in events if e.stage == "duration"]
    assert len(said) == 1 and said[0].message.endswith(" on this machine now")
    assert said[0].metrics["expected_s"] > 0.0  # said once the first frames were searched: before the solve
    assert events.index(said[0]) < next(i for i, e in enumerate(events) if e.stage == "track")
    assert res.compile_s > 0.0, "the test compiled nothing"
    phases = (res.detect_s, res.identify_s, res.estimate_s, res.check_s)
    assert min(phases) >= 0.0 and res.write_s >= 0.0, (phases, res.write_s, res.compile_s)
    assert sum(phases) == pytest.approx(res.elapsed_s, abs=1e-9), (phases, res.elapsed_s)  # the phases add up
    assert " = " in res.timing_line() and "writing" in res.timing_line()
