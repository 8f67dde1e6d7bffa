"""Two BBs in one blob: split into both centroids when the blob's shape pins them, left out when it does not."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calib.split import FrameWindows, SplitSettings, fit_pair, merged_pairs, radial_profile
from orbitct.simulator import gaussian_blur

DIAMETER_PX = 6.0
ISOLATED = np.array([[40.3, 42.1], [150.6, 40.2], [41.1, 150.8], [152.4, 148.7]])


def _frame(pair: np.ndarray, seed: int = 0) -> FrameWindows:
    """A 192 px frame of steel balls (chords supersampled 4x), blurred in intensity like a scintillator, Poisson."""
    n, over = 192, 4
    grid = (np.arange(n * over) + 0.5) / over - 0.5
    x, y = np.meshgrid(grid, grid)
    li = np.zeros_like(x)
    r = 0.5 * DIAMETER_PX
    for c in np.concatenate([ISOLATED, pair]):
        li += 0.35 * 2.0 * np.sqrt(np.maximum(r * r - (x - c[0]) ** 2 - (y - c[1]) ** 2, 0.0))
    li = li.reshape(n, over, n, over).mean((1, 3)) + 0.3 + 0.001 * np.arange(n)[None]  # a sloped background
    i0 = 20000.0
    mean = gaussian_blur((i0 * np.exp(-li)).astype(np.float32), 0.6)
    raw = np.random.default_rng(seed).poisson(mean).astype(np.uint16)
    return FrameWindows(raw, np.zeros((n, n), np.float32), np.full((n, n), i0, np.float32))


@pytest.mark.parametrize("sep_ratio", [0.8, 1.0, 1.2])
def test_a_blob_of_two_bbs_is_split_into_both_centroids(sep_ratio: float) -> None:
    s = SplitSettings(diameter_px=DIAMETER_PX)
    axis = np.array([np.cos(0.4), np.sin(0.4)])
    pair = np.array([[96.2, 95.7], [96.2, 95.7] + sep_ratio * DIAMETER_PX * axis])
    frame = _frame(pair)
    profile = radial_profile(frame, ISOLATED + np.array([0.03, -0.02]), s.radius_px)  # detected, not exact, centres
    assert profile is not None
    guess = pair + np.array([[0.6, -0.4], [-0.5, 0.5]])  # predictions through a geometry are not exact either
    fit = fit_pair(frame, guess, profile, s)
    assert fit is not None and fit.trusted(guess, s), fit
    assert np.linalg.norm(fit.uv - pair, axis=1).max() < 0.2


def test_two_bbs_almost_on_top_of_each_other_stay_out() -> None:
    s = SplitSettings(diameter_px=DIAMETER_PX)
    pair = np.array([[96.2, 95.7], [96.2 + 0.4 * DIAMETER_PX, 95.7]])
    frame = _frame(pair)
    profile = radial_profile(frame, ISOLATED, s.radius_px)
    assert profile is not None
    fit = fit_pair(frame, pair, profile, s)
    assert fit is None or not fit.trusted(pair, s)


def test_a_blob_that_is_not_two_bbs_is_not_split() -> None:
    """One larger ball where two BBs were predicted (metal, or a wrong prediction): the profile model misfits."""
    s = SplitSettings(diameter_px=DIAMETER_PX)
    frame = _frame(np.empty((0, 2)))
    n = 192
    y, x = np.mgrid[0:n, 0:n].astype(float)
    big = 0.35 * 2.0 * np.sqrt(np.maximum(36.0 - (x - 96.0) ** 2 - (y - 96.0) ** 2, 0.0))  # 12 px across
    frame.raw = np.random.default_rng(1).poisson(frame.raw * np.exp(-big)).astype(np.uint16)
    profile = radial_profile(frame, ISOLATED, s.radius_px)
    assert profile is not None
    guess = np.array([[93.0, 96.0], [99.0, 96.0]])
    fit = fit_pair(frame, guess, profile, s)
    assert fit is None or not fit.trusted(guess, s)


def test_pairs_are_the_close_predictions_with_a_missing_detection() -> None:
    pred = np.array(
        [
            [[10.0, 10.0], [14.0, 10.0], [80.0, 80.0]],
            [[10.0, 10.0], [30.0, 10.0], [80.0, 80.0]],
            [[10.0, 10.0], [14.0, 10.0], [12.0, 12.0]],
        ]
    )  # a third BB close: not a pair
    uv = np.full_like(pred, np.nan)
    uv[:, 2] = pred[:, 2]
    assert merged_pairs(pred, uv, within_px=7.5) == [(0, 0, 1)]
    assert merged_pairs(pred, pred, within_px=7.5) == []  # both detected: nothing to split


@pytest.fixture(scope="module")
def pair_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Experiment A at 384 px, BB 1 moved beside BB 0 (surfaces 3 mm apart): the views along them see one blob."""
    from orbitct.errorprofiles import make_profile
    from orbitct.phantoms.experiments import experiment_phantom
    from orbitct.simulator.scan import simulate_scan

    ph = experiment_phantom("A", 0)
    xyz = ph.markers_xyz.copy()
    tangent = np.array([-xyz[0, 1], xyz[0, 0], 0.0]) / np.hypot(xyz[0, 0], xyz[0, 1])
    xyz[1] = xyz[0] + (ph.marker_diameter_mm + 3.0) * tangent
    ph = replace(
        ph,
        markers_xyz=xyz,
        primitives=tuple(replace(p, center=xyz[1]) if p.label == "bb1" else p for p in ph.primitives),
    )
    path = tmp_path_factory.mktemp("pair") / "pair.h5"
    simulate_scan(ph, out=path, n_frames=120, detector_px=384, errors=make_profile("bench", 0, angle_scale=120 / 500))
    return path


def test_calibration_splits_the_pair_and_finds_every_bb_once(pair_scan: Path, tmp_path: Path) -> None:
    import h5py

    from calib.pipeline import calibrate_scan
    from orbitct.scanfile import ScanFile

    res = calibrate_scan(pair_scan, out=tmp_path / "c.h5")
    with ScanFile(tmp_path / "c.h5") as sf:
        proj = sf.projection_indices
        true_uv = sf.geometry("truth")[proj].project(sf.truth_markers_xyz())
    with h5py.File(tmp_path / "c.h5") as f:
        n_split = int(f["geometry/calibrated"].attrs["split_blobs"])
    assert res.n_bbs == 8  # no pseudo-BB for the blob of two
    uv = res.uv[proj]
    d = np.linalg.norm(uv[:, :, None] - true_uv[:, None], axis=-1)
    d[~np.isfinite(d)] = np.inf
    owner = [int(np.bincount(d[np.isfinite(uv[:, k, 0]), k].argmin(1), minlength=8).argmax()) for k in range(8)]
    assert sorted(owner) == list(range(8))
    k0, k1 = owner.index(0), owner.index(1)
    sep = np.linalg.norm(true_uv[:, 0] - true_uv[:, 1], axis=-1)
    d_px = 4.36  # 3.17 mm BBs at this magnification and pitch
    merged = sep < 1.25 * d_px
    both = merged & np.isfinite(uv[:, k0, 0]) & np.isfinite(uv[:, k1, 0])
    assert n_split > 0 and both.sum() >= 10, (n_split, both.sum(), merged.sum())
    err = np.linalg.norm(uv[both][:, [k0, k1]] - true_uv[both][:, [0, 1]], axis=-1)
    assert np.sqrt(np.mean(err**2)) < 0.35, err
