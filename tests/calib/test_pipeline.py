"""End to end on simulated scans of the paper's experiments (small sizes): identity, accuracy, files, CLI."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

import calib
from calib.evaluate import similarity_aligned_error_px
from orbitct.scanfile import ScanFile

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
def test_every_bb_found_once_with_its_identity(simulated_scan: Callable[..., Path], tmp_path: Path, experiment: str, n_bbs: int) -> None:
    scan = simulated_scan(experiment)
    res = calib.calibrate_scan(scan, out=tmp_path / "out.h5")
    proj, truth_uv, truth = _truth(scan)
    owner, purity, worst = _identity(res.uv[proj], truth_uv[proj])
    assert res.n_bbs == n_bbs
    assert sorted(owner.tolist()) == list(range(n_bbs))
    assert purity == 1.0
    assert worst < 2.0  # no wrong blob: every kept detection is near its own BB
    assert np.isfinite(res.uv[proj]).all(-1).mean() > 0.85
    # 192 px: a BB spans 2.2 px and its centroids scatter ~0.4 px RMS among the clutter (4x the 768 px
    # benchmark scale, where the bound is 0.15 px); 0.45 px here is the same accuracy relative to the noise.
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj])
    assert err < 0.45
    assert res.iterations[-1].rpe_mean_mm < 0.1 * res.iterations[0].rpe_mean_mm


def test_metal_and_small_bbs_are_nan_rather_than_wrong(simulated_scan: Callable[..., Path], tmp_path: Path) -> None:
    scan = simulated_scan("C", 384, 120)  # 2 mm BBs need 384 px to span 2.7 px
    res = calib.calibrate_scan(scan, out=tmp_path / "c.h5")
    proj, truth_uv, truth = _truth(scan)
    owner, purity, worst = _identity(res.uv[proj], truth_uv[proj])
    assert res.n_bbs == 10 and sorted(owner.tolist()) == list(range(10))
    assert purity == 1.0 and worst < 2.0
    seen = np.isfinite(res.uv[proj]).all(-1)
    assert 0.6 < seen.mean() < 0.99  # some BBs hidden by screws, spine or each other are left out
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj])
    assert err < 0.3


def test_paper_method_converges_in_two_iterations(simulated_scan: Callable[..., Path], tmp_path: Path) -> None:
    res = calib.calibrate_scan(simulated_scan("A"), method="paper", out=tmp_path / "p.h5", iterations=3)
    m = [s.rpe_mean_mm for s in res.iterations]
    assert len(m) == 4
    assert m[1] < 0.2 * m[0]
    assert m[1] - m[2] < 0.25 * m[1]
    assert abs(m[2] - m[3]) < 0.05 * m[2]


def test_results_written_as_scan_file_says(simulated_scan: Callable[..., Path], tmp_path: Path) -> None:
    src = simulated_scan("A")
    before = src.stat().st_mtime_ns
    out = tmp_path / "copy.h5"
    res = calib.calibrate_scan(src, out=out, report_dir=tmp_path / "rep")
    assert src.stat().st_mtime_ns == before
    with h5py.File(src) as f:
        assert "geometry/calibrated" not in f
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
    for name in ("table1.md", "table1.csv", "rpe_violin.png", "corrections.png"):
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
    with ScanFile(scan) as sf:
        assert sf.h5["geometry/calibrated"].attrs["method"] == "paper"
    r = CliRunner().invoke(cli, ["calibrate", str(scan), "--method", "magic"])
    assert r.exit_code != 0


def test_the_predicted_error_tracks_the_true_one_and_fails_the_poor_views(simulated_scan: Callable[..., Path],
                                                                          tmp_path: Path) -> None:
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


def test_twice_the_bench_errors_are_recovered_by_tracking_with_larger_jumps(tmp_path: Path) -> None:
    """Errors twice the published bench profile: the BBs are lost with the expected 3 mm jitter; tracking again
    with larger allowed jumps recovers them, the calibration reaches the accuracy of the 1x case, and says so."""
    from orbitct.errorprofiles import make_profile
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "x2.h5"
    simulate_scan("A", out=scan, n_frames=250, detector_px=256, seed=1, overwrite=True,
                  errors=make_profile("bench", 1, angle_scale=2 * 250 / 500, shift_amplitude_mm=16.0, shift_noise_mm=4.0))
    first = calib.calibrate_scan(scan, out=tmp_path / "no.h5", recover=False)
    assert first.quality is not None and not first.quality.passed
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    proj, _, truth = _truth(scan)
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj])
    assert res.quality is not None and res.quality.passed and res.quality.counts["own"] == proj.size
    assert err < 0.3
    assert any("allowing" in w and "mm jumps" in w for w in res.warnings)


def test_four_times_the_bench_errors_calibrate_to_the_floor(tmp_path: Path) -> None:
    """Errors four times the bench profile (about 4 deg and 40 mm; frames jump farther than the BBs lie apart):
    every BB keeps its identity, every view is calibrated from its own BBs, as accurately as at 1x."""
    from orbitct.errorprofiles import make_profile
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "x4.h5"
    simulate_scan("A", out=scan, n_frames=250, detector_px=256, seed=1, overwrite=True,
                  errors=make_profile("bench", 1, angle_scale=4 * 250 / 500, shift_amplitude_mm=32.0, shift_noise_mm=8.0))
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    proj, truth_uv, truth = _truth(scan)
    owner, purity, worst = _identity(res.uv[proj], truth_uv[proj])
    assert res.n_bbs == 8 and sorted(owner.tolist()) == list(range(8)) and purity == 1.0 and worst < 1.0
    err, _ = similarity_aligned_error_px(res.geometry[proj], truth[proj])
    assert res.quality is not None and res.quality.passed and res.quality.counts["own"] == proj.size
    assert err < 0.3


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
    simulate_scan(experiment_phantom("C"), resolve_orbit("C", None, 206), out=scan, detector_px=512, seed=seed,
                  errors=make_profile("bench", seed, angle_scale=206 / 500))
    res = calib.calibrate_scan(scan, out=tmp_path / "o.h5")
    proj, _, truth = _truth(scan)
    err, per = similarity_aligned_error_px(res.geometry[proj], truth[proj], max_views=proj.size)
    assert res.quality is not None and res.quality.passed, res.quality.reasons
    assert res.quality.counts["own"] >= 0.97 * proj.size and err < 0.2
    assert np.nanmax(per) < 1.0, np.flatnonzero(per > 1.0)


def test_a_truncating_panel_uses_bbs_up_to_its_edge_and_flags_what_it_cannot_see(tmp_path: Path) -> None:
    """A 384 px panel with the native 768-px pitch sees half the field: BBs enter and leave all the time.
    Views with four or more whole BBs are calibrated from them (BBs detected up to the panel's edge); the
    others are bridged, and any view whose geometry is off by more than 1 px is flagged by its prediction."""
    from orbitct.errorprofiles import make_profile
    from orbitct.simulator.scan import simulate_scan

    scan = tmp_path / "cut.h5"
    simulate_scan("A", out=scan, n_frames=120, detector_px=384, pitch_mm=427.0 / 768, seed=0, overwrite=True,
                  errors=make_profile("bench", 0, angle_scale=120 / 500))
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
