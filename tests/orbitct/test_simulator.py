"""Projection simulator: exact line integrals, detector noise model, simulated bench."""

import numpy as np
import pytest

from orbitct.geometry import GeometryError, Panel, ViewGeometry
from orbitct.orbits import make_orbit
from orbitct.phantoms import Phantom, cylinder, experiment_phantom, sphere
from orbitct.rotations import rotvec_to_matrix
from orbitct.simulator import (
    DetectorModel,
    SimulatedBench,
    line_integral_stack,
    line_integrals,
)
from orbitct.simulator.noise import poisson_array

DET = Panel(48, 64, 427 / 64, 427 / 48 * 0.75)


def _pixel_rays(g: ViewGeometry, i: int) -> tuple[np.ndarray, np.ndarray]:
    rr, cc = np.meshgrid(np.arange(g.panel.rows), np.arange(g.panel.cols), indexing="ij")
    px = np.stack([cc.ravel(), rr.ravel()], -1).astype(float)
    pts = g[i].pixel_to_point(px[None])[0]
    return np.broadcast_to(g.S[i], pts.shape), pts - g.S[i]


@pytest.mark.parametrize("experiment", ["A", "C"])
def test_line_integrals_equal_exact_chords_at_pixel_centres(experiment: str) -> None:
    p = experiment_phantom(experiment)
    o = make_orbit("sawtooth", n_frames=7)
    g = o.nominal_geometry(785.0, 1200.0, DET).transformed(rotvec_to_matrix([0.02, -0.03, 0.01]), [3.0, -2.0, 5.0])
    for i in (0, 3):
        img = line_integrals(p, g, i, supersample=False)
        o_, d_ = _pixel_rays(g, i)
        ref = p.line_integral(o_, d_).reshape(DET.shape)
        assert img.dtype == np.float32 and img.shape == DET.shape
        assert np.allclose(img, ref, rtol=2e-6, atol=2e-6)


def test_partly_off_detector_and_behind_source() -> None:
    g = ViewGeometry.from_carm(0.0, 0.0, 785.0, 1200.0, DET)
    # a sphere whose projection is cut by the detector edge
    p = Phantom("edge", (sphere((120.0, 0.0, 0.0), 40.0, mu=0.02),))
    img = line_integrals(p, g, 0, supersample=False)
    o_, d_ = _pixel_rays(g, 0)
    assert img[:, -1].max() > 0 and np.allclose(img, p.line_integral(o_, d_).reshape(DET.shape), atol=1e-6)
    # a long cylinder reaching behind the source: footprint falls back to the whole detector
    q = Phantom("long", (cylinder((0.0, -700.0, 0.0), (0, 1, 0), 5.0, 400.0, mu=0.01),))
    img = line_integrals(q, g, 0, supersample=False)
    assert np.allclose(img, q.line_integral(o_, d_).reshape(DET.shape), atol=1e-6)
    with pytest.raises(GeometryError, match="out of range"):
        line_integrals(q, g, 5)
    with pytest.raises(GeometryError, match="non-finite"):
        line_integrals(q, ViewGeometry.empty_like(1, DET), 0)


def test_supersampling_preserves_bb_mass() -> None:
    bench = SimulatedBench()
    p = Phantom("bb", (sphere((0, 0, 0), 3.17 / 2, material="steel"),))
    view = bench.lab_view
    a = line_integrals(p, view, 0, supersample=True)
    b = line_integrals(p, view, 0, supersample=8)
    # integral over the detector = mu * volume * magnification^2 / pixel area (cone beam, small object)
    m = bench.magnification
    expect = 0.8 * 4 / 3 * np.pi * (3.17 / 2) ** 3 * m**2 / bench.panel.pitch_col**2
    assert a.sum() == pytest.approx(expect, rel=0.01) and b.sum() == pytest.approx(expect, rel=0.005)


def test_bb_clearly_visible_over_clutter_in_raw_frames() -> None:
    """With the default detector model a 3.17 mm BB stands out of phantom A's clutter."""
    bench = SimulatedBench()  # the default 768 px panel
    p = experiment_phantom("A", seed=0)
    R, t = np.eye(3), np.zeros(3)
    raw = bench.render(p, R, t, rng=1)
    flat, dark = bench.model.maps(bench.panel.shape)
    li = -np.log(np.maximum(raw - dark, 0.5) / flat)
    uv = bench.view(R, t).project(p.markers_xyz)[0]
    seen = 0
    for c, r in uv:
        ic, ir = int(round(c)), int(round(r))
        if not (16 <= ic < 752 and 16 <= ir < 752):
            continue
        core = li[ir - 1 : ir + 2, ic - 1 : ic + 2].mean()
        box = li[ir - 12 : ir + 13, ic - 12 : ic + 13]
        ring = np.concatenate([box[0], box[-1], box[:, 0], box[:, -1]])
        assert core - np.median(ring) > 1.2  # a 3.17 mm steel BB adds ~2 units of line integral
        assert core - np.median(ring) > 5 * ring.std()  # well above clutter and noise
        seen += 1
    assert seen >= 6


def test_detector_model_statistics() -> None:
    model = DetectorModel(blur_sigma_px=0.0, gain_variation=0.0, falloff=0.0, dark_pattern_adu=0.0)
    shape = (200, 200)
    rng = np.random.default_rng(0)
    li = np.full(shape, 2.0, np.float32)
    raw = model.expose(li, rng).astype(float)
    mean = 16000 * np.exp(-2.0)
    assert raw.mean() == pytest.approx(mean + 300, rel=0.003)
    assert raw.var() == pytest.approx(4.0 * mean + 3.0**2, rel=0.03)  # gain * signal (Poisson) + read noise
    dark = model.dark(rng, shape).astype(float)
    assert dark.mean() == pytest.approx(300, abs=0.05) and dark.std() == pytest.approx(3.0, rel=0.03)
    flat = model.flat(rng, shape)
    assert flat.dtype == np.uint16 and flat.mean() == pytest.approx(16300, rel=0.002)
    # saturation and reproducibility
    hot = DetectorModel(flat_counts=65000, dark_offset_adu=3000).flat(np.random.default_rng(1), (8, 8))
    assert hot.max() == 65535
    a = model.expose(li, np.random.default_rng(5))
    assert np.array_equal(a, model.expose(li, np.random.default_rng(5)))


def test_scatter_adds_a_smooth_signal_that_peaks_behind_one_attenuation_length() -> None:
    plain = DetectorModel(blur_sigma_px=0.0, gain_variation=0.0, falloff=0.0)
    scattering = plain.model_copy(update={"scatter_fraction": 0.5})
    li = np.zeros((128, 128), np.float32)
    li[32:96, 32:96] = 1.0  # one attenuation length in the middle, open field around it
    added = scattering.mean_signal(li) - plain.mean_signal(li)
    assert added.min() >= 0.0 and plain.scatter(li).max() == 0.0
    # wide (its std 8 % of the panel, 10 px): 12 px outside the object there is still scatter; it varies slowly
    edge_step = np.abs(np.diff(plain.mean_signal(li), axis=1)).max()
    assert added[64, 20] > 0.05 * added[64, 64] and np.abs(np.diff(added, axis=1)).max() < 0.05 * edge_step
    # l * exp(-l) at l = 1: behind the middle of an object much wider than the spread, the fraction of the field
    assert 0.5 * 16000 * np.exp(-1.0) * 0.9 < added[64, 64] < 0.5 * 16000 * np.exp(-1.0) * 1.01


def test_lag_carries_a_share_of_each_frame_into_the_next_and_shows_in_a_dark_after_it() -> None:
    model = DetectorModel(blur_sigma_px=0.0, gain_variation=0.0, falloff=0.0, lag_fraction=0.05, read_noise_adu=0.0)
    rng = np.random.default_rng(0)
    shape = (64, 64)
    first = model.flat(rng, shape).astype(float)  # nothing before it: a share held back
    assert first.mean() == pytest.approx(300 + 0.95 * 16000, rel=0.003)
    second = model.flat(rng, shape).astype(float)  # gets the share of the first back
    assert second.mean() == pytest.approx(300 + 16000, rel=0.003)
    ghost = model.dark(rng, shape).astype(float)
    assert ghost.mean() == pytest.approx(300 + 0.05 * 16000, rel=0.02)
    assert model.dark(rng, shape).astype(float).mean() == pytest.approx(300, abs=1.0)  # gone after one frame


def test_dead_pixels_and_columns_read_their_dark_offset_at_the_same_place_in_every_frame() -> None:
    model = DetectorModel(dead_pixel_fraction=0.01, dead_columns=2)
    shape = (100, 120)
    dead = model.dead(shape)
    assert dead.all(axis=0).sum() == 2 and 0.005 < dead[:, ~dead.all(axis=0)].mean() < 0.02
    _, dark = model.maps(shape)
    for seed in (1, 2):
        flat = model.flat(np.random.default_rng(seed), shape)
        assert np.array_equal(flat[dead], np.rint(dark[dead]).astype(np.uint16))
        assert flat[~dead].min() > 5000
    assert np.array_equal(DetectorModel(dead_pixel_fraction=0.01, dead_columns=2).dead(shape), dead)


def test_presets_name_the_clean_and_the_realistic_panel_and_refuse_others() -> None:
    assert DetectorModel.preset("clean") == DetectorModel()
    real = DetectorModel.preset("realistic")
    assert real.scatter_fraction > 0 and real.lag_fraction > 0 and real.dead_columns > 0
    with pytest.raises(ValueError, match="unknown detector preset 'grainy'"):
        DetectorModel.preset("grainy")


def test_the_focal_spot_blurs_the_same_millimetres_on_any_pixel_pitch() -> None:
    spot = DetectorModel(blur_sigma_px=0.0, gain_variation=0.0, falloff=0.0, focal_blur_mm=0.5)

    def edge_width_mm(pitch_mm: float, n: int) -> float:
        li = np.zeros((8, n), np.float32)
        li[:, n // 2 :] = 1.0
        row = spot.mean_signal(li, pitch_mm)[4].astype(float)
        t = (row[0] - row) / (row[0] - row[-1])  # 0 to 1 across the edge
        return float(np.interp(0.9, t, np.arange(n)) - np.interp(0.1, t, np.arange(n))) * pitch_mm

    fine, coarse = edge_width_mm(0.25, 128), edge_width_mm(0.5, 64)
    assert fine == pytest.approx(2.563 * 0.5, rel=0.05)  # 10-90 % of a Gaussian edge: 2.563 sigma
    assert coarse == pytest.approx(fine, rel=0.1)
    # the realistic panel: 1.0 px in all on the reference panel, less in pixels on larger ones
    real = DetectorModel.preset("realistic")
    assert real.blur_px() == pytest.approx(1.0)
    assert 0.6 < real.blur_px(2 * 0.556) < 0.8


def test_blur_keeps_mean_and_smooths() -> None:
    sharp = DetectorModel(blur_sigma_px=0.0)
    soft = DetectorModel(blur_sigma_px=1.5)
    li = np.zeros((64, 64), np.float32)
    li[:, 32:] = 3.0
    e1, e2 = sharp.mean_signal(li), soft.mean_signal(li)
    assert e2.sum() == pytest.approx(e1.sum(), rel=1e-3)
    assert np.abs(np.diff(e2, axis=1)).max() < 0.5 * np.abs(np.diff(e1, axis=1)).max()


@pytest.mark.parametrize("lam", [0.3, 4.0, 11.9, 12.0, 60.0, 4000.0])
def test_poisson_kernel(lam: float) -> None:
    n = 40000
    seed = np.uint64(12345)
    x = poisson_array(np.full(n, lam), seed)
    assert x.mean() == pytest.approx(lam, abs=5 * np.sqrt(lam / n))
    assert x.var() == pytest.approx(lam, rel=0.05)
    assert np.all(x == np.floor(x)) and x.min() >= 0


def test_bench_renders_object_pose() -> None:
    bench = SimulatedBench.with_panel(64)
    assert bench.panel.pitch_col == pytest.approx(427.0 / 64)
    p = experiment_phantom("B")
    R = rotvec_to_matrix([0.1, 0.0, 0.4])
    t = np.array([2.0, 1.0, -3.0])
    v = bench.view(R, t)
    assert v.allclose(ViewGeometry.from_object_poses(bench.lab_view, R, t))
    assert np.array_equal(bench.line_integrals(p, R, t), line_integrals(p, v, 0))
    raw = bench.render(p, R, t, rng=3)
    assert raw.dtype == np.uint16 and raw.shape == (64, 64)
    assert bench.dark(0).mean() < 400 and bench.flat(0).mean() > 10000
    assert bench.config()["sad_mm"] == 785.0


def test_line_integral_stack_skips_non_projection_views() -> None:
    p = experiment_phantom("B")
    g = ViewGeometry.empty_like(2, DET).concatenate(
        make_orbit("circular", n_frames=3).nominal_geometry(785.0, 1200.0, DET)
    )
    stack = line_integral_stack(p, g)
    assert stack.shape == (3,) + DET.shape
    assert np.array_equal(stack[1], line_integrals(p, g, 3))


@pytest.mark.parametrize("axis, x0", [((0, 0, 1), 0.0), ((0, 0, 1), 0.1), ((0.3, 0.2, 1), 0.0), ((1, 0, 0.2), 0.05)])
def test_thin_wire_projects_its_mass(axis: tuple, x0: float) -> None:
    """A 0.13 mm wire (thinner than a pixel) projects by its mass: pixel averages, no sampling gaps."""
    bench = SimulatedBench()
    wire = Phantom("w", (cylinder((x0, 0, 0), axis, 0.065, 100.0, material="tungsten"),))
    g = ViewGeometry.from_carm(0.7, 0.4, 785.0, 1200.0, bench.panel)
    img = line_integrals(wire, g, 0)
    fine = line_integrals(wire, g, 0, supersample=24)
    assert np.abs(img - fine).sum() < 0.06 * fine.sum()
    # every pixel along the wire sees it: no gaps between the rows it crosses
    hit = img > 0.02
    assert hit.any(axis=1).sum() > 0.9 * np.ptp(np.flatnonzero(hit.any(axis=1)))


def test_the_scintillators_share_of_the_blur_correlates_the_noise_and_keeps_the_image() -> None:
    li = np.full((96, 96), 1.0, np.float32)
    seen = {}
    for noise_blur in (0.0, 0.8):
        model = DetectorModel(blur_sigma_px=1.0, noise_blur_px=noise_blur)
        rng = np.random.default_rng(2)
        a, b = (model.expose(li, rng).astype(float) for _ in range(2))
        d = (a - b) / np.sqrt(2.0)
        seen[noise_blur] = (a.mean(), np.corrcoef(d[:, :-1].ravel(), d[:, 1:].ravel())[0, 1])
    assert abs(seen[0.8][0] / seen[0.0][0] - 1) < 1e-3  # the same image on average
    assert abs(seen[0.0][1]) < 0.05 and seen[0.8][1] > 0.4  # independent pixels; correlated neighbours
    with pytest.raises(ValueError, match="noise_blur_px .* is part of blur_sigma_px"):
        DetectorModel(blur_sigma_px=0.6, noise_blur_px=1.0)
