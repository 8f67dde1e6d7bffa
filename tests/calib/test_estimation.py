"""Estimation on exact synthetic BB projections (no pixels): bundle, paper, gauge, rays."""

from __future__ import annotations

import numpy as np
import pytest

from calib.bundle import bundle_adjust, gauge_matrix
from calib.evaluate import similarity_aligned_error_px, truth_fed_error_px
from calib.model import ViewModel
from calib.paper import paper_calibrate
from calib.rays import (
    marker_rays,
    pairwise_midpoint_mean,
    point_ray_distance,
    rpe_per_frame,
    triangulate_least_squares,
)
from tests.helpers.calib_scans import perturbed, sawtooth, spiral_markers


def _problem(n: int = 200, size: int = 768, noise_px: float = 0.05, k: int = 8, seed: int = 1):
    nominal = sawtooth(n, size)
    truth = perturbed(nominal, seed=seed)
    xyz = spiral_markers(k)
    uv = truth.project(xyz) + np.random.default_rng(seed).normal(0.0, noise_px, (n, k, 2))
    return nominal, truth, xyz, uv


def test_bundle_recovers_truth_from_noisy_true_projections() -> None:
    nominal, truth, _, uv = _problem()
    model = ViewModel(nominal)
    xyz0 = triangulate_least_squares(*marker_rays(nominal, uv))
    res = bundle_adjust(model, uv, xyz0)
    est = model.geometry(res.state)
    err, _ = similarity_aligned_error_px(est, truth)
    assert similarity_aligned_error_px(nominal, truth)[0] > 5.0
    assert err < 0.1
    resid = np.linalg.norm(est.project(res.xyz) - uv, axis=-1)
    assert np.sqrt(np.mean(resid**2)) < 0.07  # about the centroid noise (0.05 px per axis)


def test_truth_fed_error_takes_each_detected_column_for_its_true_bb_and_keeps_what_was_not_seen() -> None:
    """The reference a benchmark compares with: detections in shuffled columns, some unseen, 0.2 px off the truth;
    fed back as the true projections of their BBs (plus chosen noise) the same views calibrate to the truth."""
    nominal, truth, xyz, _ = _problem(n=120)
    rng = np.random.default_rng(3)
    order = rng.permutation(len(xyz))
    uv = truth.project(xyz)[:, order] + rng.normal(0.0, 0.2, (120, len(xyz), 2))
    uv[rng.random(uv.shape[:2]) < 0.1] = np.nan
    exact, own = truth_fed_error_px(uv, truth, xyz, nominal, noise_px=0.0)
    assert own == pytest.approx(0.2, rel=0.05)
    assert exact < 1e-3
    noisy, _ = truth_fed_error_px(uv, truth, xyz, nominal)  # the detections' own noise
    assert 0.05 < noisy < 0.5


def test_gauge_keeps_constellation_of_nominal_triangulation() -> None:
    nominal, _, _, uv = _problem(n=120)
    xyz0 = triangulate_least_squares(*marker_rays(nominal, uv))
    res = bundle_adjust(ViewModel(nominal), uv, xyz0)
    g = gauge_matrix(xyz0) @ (res.xyz - xyz0).ravel()
    assert np.abs(g).max() < 1e-6
    assert np.allclose(res.xyz.mean(0), xyz0.mean(0), atol=1e-5)


def test_bundle_with_free_intrinsics_fits_a_changing_detector() -> None:
    """Per-view SDD and piercing point changes: the free model fits them to the noise level; a constant
    detector offset is nearly a pose change (pinhole degeneracy), so accuracy is compared, not gained."""
    nominal, truth, xyz, _ = _problem(n=150)
    vec = truth.vectors.copy()
    s = np.linspace(0, 2 * np.pi, 150)[:, None]
    u_hat = truth.u / np.linalg.norm(truth.u, axis=1, keepdims=True)
    vec[:, 3:6] += 8.0 * np.sin(s) * truth.normal + 3.0 * np.cos(2 * s) * u_hat
    truth2 = truth.with_vectors(vec)
    uv = truth2.project(xyz) + np.random.default_rng(3).normal(0.0, 0.05, (150, 8, 2))
    xyz0 = triangulate_least_squares(*marker_rays(nominal, uv))
    free = ViewModel(nominal, "sdd+pp")
    res = bundle_adjust(free, uv, xyz0, intrinsics_prior_mm=20.0)
    est = free.geometry(res.state)
    resid = np.linalg.norm(est.project(res.xyz) - uv, axis=-1)
    assert np.sqrt(np.mean(resid**2)) < 0.07
    assert similarity_aligned_error_px(est, truth2)[0] < 0.3


def test_paper_method_converges_like_the_paper() -> None:
    nominal, truth, _, uv = _problem(n=150)
    model = ViewModel(nominal)
    means: list[float] = []
    paper_calibrate(
        model,
        uv,
        iterations=3,
        callback=lambda i, s, x: means.append(float(np.nanmean(rpe_per_frame(model.geometry(s), uv, x)))),
    )
    assert len(means) == 4
    assert means[1] < 0.05 * means[0]  # large drop after the first iteration
    assert abs(means[2] - means[1]) < 0.5 * means[1]  # little change after the second
    assert abs(means[3] - means[2]) < 0.2 * means[2]


def test_rpe_is_mean_point_to_ray_distance() -> None:
    nominal, truth, xyz, uv = _problem(n=5, noise_px=0.0)
    assert np.nanmax(rpe_per_frame(truth, uv, xyz)) < 1e-6
    uv2 = uv.copy()
    uv2[0, 0, 0] += 10.0
    uv2[1, :, :] = np.nan
    rpe = rpe_per_frame(truth, uv2, xyz)
    o, d = truth[0].backproject(uv2[0:1, 0:1])
    assert rpe[0] == pytest.approx(point_ray_distance(xyz[0], o[0, 0], d[0, 0]) / 8, rel=1e-6)
    assert np.isnan(rpe[1])


def test_pairwise_midpoints_of_rays_through_a_point() -> None:
    nominal, truth, xyz, uv = _problem(n=12, noise_px=0.0)
    got = pairwise_midpoint_mean(*marker_rays(truth, uv))
    assert np.allclose(got, xyz, atol=1e-6)


def test_a_detection_with_a_larger_spread_pulls_the_bundle_less() -> None:
    """``spread`` divides each residual: one BB's detections 1.5 px off in half the views move the solution far
    less when the bundle is told they are five times as noisy as the rest (as a BB over the outline is)."""
    nominal, truth, xyz, uv = _problem(n=120, noise_px=0.02)
    off = uv.copy()
    off[::2, 3] += np.array([1.5, -1.0])
    model = ViewModel(nominal)
    xyz0 = triangulate_least_squares(*marker_rays(nominal, off))
    spread = np.ones(uv.shape[:2])
    spread[:, 3] = 5.0
    alike = similarity_aligned_error_px(model.geometry(bundle_adjust(model, off, xyz0).state), truth)[0]
    weighted = similarity_aligned_error_px(model.geometry(bundle_adjust(model, off, xyz0, spread=spread).state), truth)[
        0
    ]
    assert weighted < 0.5 * alike
    # a spread alike for every detection is no weighting at all: the same solution
    same = bundle_adjust(model, uv, xyz0, spread=np.full(uv.shape[:2], 1.0))
    plain = bundle_adjust(model, uv, xyz0)
    assert np.allclose(same.xyz, plain.xyz) and np.allclose(same.state.t, plain.state.t)
