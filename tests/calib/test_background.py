"""What the object puts behind a BB: the photons left and the centroid shift of a background that is no plane."""

from __future__ import annotations

import numpy as np
import pytest

from calib.background import ObjectBackground, phantom_background
from calib.detect import _refine
from calib.plan import predict_placement
from calib.surfaces import EllipticCylinder
from orbitct.geometry import ViewGeometry
from orbitct.phantoms.phantom import Phantom
from orbitct.phantoms.primitives import cylinder
from orbitct.simulator.projector import line_integrals
from tests.helpers.calib_scans import sawtooth, spiral_markers

D_MM = 3.17


def _body(radius_mm: float = 60.0) -> Phantom:
    return Phantom(
        "body",
        (cylinder((0, 0, 0), (0, 0, 1), radius_mm, 300.0, material="tissue", label="body"),),
        np.zeros((0, 3)),
        D_MM,
        "",
    )


def _shift(background: ObjectBackground, geometry: ViewGeometry, xyz: np.ndarray) -> np.ndarray:
    """The computed centroid shifts ``(P, K, 2)`` (px)."""
    return background._computed(geometry, xyz, D_MM)[1]


class _Grazing:
    """One view of a tissue cylinder (60 mm) and BBs where the ray from the source grazes its outline, ``off`` mm
    outside it (negative: inside); the noise-free frames the detector refines them on."""

    def __init__(self) -> None:
        self.g = sawtooth(8, 256)[:1]
        self.body = _body()
        self.source = self.g.S[0]
        self.tangent = np.arctan2(self.source[1], self.source[0]) + np.arccos(60.0 / np.linalg.norm(self.source[:2]))
        self.bg = ObjectBackground.of(self.body.line_integral, self.g, EllipticCylinder(60.0, 60.0, -50.0, 50.0), D_MM)
        self.flat, self.dark = np.full(self.g.panel.shape, 1e4, np.float32), np.zeros(self.g.panel.shape, np.float32)

    def bb(self, off: float) -> np.ndarray:
        return (60.0 + D_MM / 2 + off) * np.array([np.cos(self.tangent), np.sin(self.tangent), 0.0]) + [0.0, 0.0, 10.0]

    def refine(self, phantom: Phantom, c: np.ndarray) -> np.ndarray:
        """The detector's record (``_refine``) for the BB at ``c`` on the noise-free frame of ``phantom``."""
        uv = self.g.project(c[None])[0, 0]
        d_px = D_MM * np.linalg.norm(self.g.pixel_to_point(uv[None, None])[0, 0] - self.source)
        d_px /= np.linalg.norm(c - self.source) * self.g.panel.pitch_col
        raw = (self.flat * np.exp(-line_integrals(phantom, self.g, 0))).astype(np.float32)
        return _refine(raw, self.dark, self.flat, float(uv[0]), float(uv[1]), 0.5 * d_px, int(np.ceil(d_px)) + 2, 3)


def test_the_centroid_shift_over_the_objects_edge_is_the_detectors() -> None:
    """A BB where the ray grazes a tissue cylinder, from 1 mm inside to 3 mm outside its outline: the computed
    shift is the detector's own (``_refine`` on the noise-free frame, less its result for the BB alone)."""
    view = _Grazing()
    computed, measured = [], []
    for off in (-1.0, 0.0, 1.0, 2.0, 3.0):
        c = view.bb(off)
        both = view.body.with_markers(c[None])
        alone = both.subset([str(p.label).startswith("bb") for p in both.primitives])
        measured.append(view.refine(both, c)[:2] - view.refine(alone, c)[:2])
        computed.append(_shift(view.bg, view.g, c[None])[0, 0])
    measured, computed = np.array(measured), np.array(computed)
    assert np.abs(measured).max() > 0.04  # the edge does shift the centroid
    np.testing.assert_allclose(computed[1:], measured[1:], atol=0.01)
    assert np.sign(computed[0, 0]) == np.sign(measured[0, 0]) and abs(computed[0, 0] - measured[0, 0]) < 0.025


def test_the_background_rms_over_the_objects_edge_is_the_detectors() -> None:
    """The background RMS the bundle weights a detection by (``background_rms``), predicted for BBs from 2 mm
    inside the outline of a tissue cylinder to well clear of it: on noise-free frames the structure the plane
    leaves is the detector's own (``_refine`` on the frame), and it is largest where the outline crosses."""
    view = _Grazing()
    predicted, measured = [], []
    for off in (-2.0, 0.0, 1.0, 3.0, 8.0):
        c = view.bb(off)
        measured.append(view.refine(view.body.with_markers(c[None]), c)[5])
        predicted.append(view.bg.background_rms(view.g, c[None], D_MM, 1e-9)[0, 0])
    measured, predicted = np.array(measured), np.array(predicted)
    assert measured[1] > 5 * measured[-1]  # the outline in the window: far rougher than the air beside it
    np.testing.assert_allclose(predicted, measured, rtol=0.25, atol=2e-3)


def test_the_photon_factor_follows_the_thickness_and_averages_one_over_the_surface() -> None:
    """Relative noise variance ``exp(L - reference)``: the reference is where ``exp(L)`` has its mean over points
    spread on the surface; a BB seen through more of the object is noisier."""
    g = sawtooth(40, 256)
    body = _body(70.0)
    surface = EllipticCylinder(70.0, 70.0, -40.0, 40.0)
    bg = ObjectBackground.of(body.line_integral, g, surface, D_MM)
    xyz = spiral_markers(8, radius=70.0 + D_MM / 2)
    var = bg.variance(g, xyz, D_MM, 0.1)
    photons = bg._computed(g, xyz, D_MM)[0]
    direction = xyz[None] - g.S[:, None]
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    through = body.line_integral(np.repeat(g.S, len(xyz), 0), direction.reshape(-1, 3)).reshape(photons.shape)
    deep = through > np.quantile(through, 0.8)
    shallow = through < np.quantile(through, 0.2)
    assert photons[deep].min() > photons[shallow].max()
    np.testing.assert_allclose(np.log(photons[deep]), through[deep] - bg.reference, atol=0.15)
    assert 0.5 < float(np.mean(photons)) < 2.0
    assert np.all(np.linalg.eigvalsh(var) > 0)


def test_a_bb_over_bone_edges_is_predicted_worse_than_over_soft_tissue() -> None:
    """A dense rod just inside the surface, along the object's axis: BBs taped over it see its edges cross their
    detection windows in many views; their shifts grow beyond the object's own (its outline), BBs a quarter turn
    away keep theirs, and a placement with two BBs over the rod is predicted worse than without the rod."""
    g = sawtooth(60, 256)
    surface = EllipticCylinder(70.0, 70.0, -40.0, 40.0)
    body = cylinder((0, 0, 0), (0, 0, 1), 70.0, 300.0, material="tissue", label="body")
    rod = cylinder((60.0, 0.0, 0.0), (0, 0, 1), 6.0, 300.0, material="cortical", label="rod")
    plain = phantom_background(Phantom("plain", (body,), np.zeros((0, 3)), D_MM, ""), g, surface)
    bony = phantom_background(Phantom("rod", (body, rod), np.zeros((0, 3)), D_MM, ""), g, surface)
    angles = np.radians([0.0, 3.0, -3.0, 2.0, -2.0, 1.0])  # over the rod
    z = np.linspace(-30.0, 30.0, angles.size)
    over, away = surface.points(angles, z, D_MM), surface.points(angles + np.pi / 2, z, D_MM)

    def rms(bg: ObjectBackground, xyz: np.ndarray) -> float:
        return float(np.sqrt((_shift(bg, g, xyz) ** 2).sum(-1).mean()))

    assert rms(bony, over) > 1.3 * rms(plain, over)
    assert rms(bony, away) == pytest.approx(rms(plain, away), rel=0.1)
    xyz = np.vstack([over[:2], spiral_markers(6, radius=70.0 + D_MM / 2)])
    with_rod = predict_placement(g, xyz, D_MM, surface=surface, background=bony).summary()["predicted_px_rms"]
    without = predict_placement(g, xyz, D_MM, surface=surface, background=plain).summary()["predicted_px_rms"]
    assert with_rod > without


def test_the_random_noise_is_what_a_reported_noise_leaves_after_the_typical_shifts() -> None:
    """A calibration's centroid noise is the robust RMS of all residuals, shifts included: the photons' share is
    what makes BBs spread on the surface report it; smaller over bone than over soft tissue alone."""
    g = sawtooth(40, 256)
    surface = EllipticCylinder(70.0, 70.0, -40.0, 40.0)
    body = cylinder((0, 0, 0), (0, 0, 1), 70.0, 300.0, material="tissue", label="body")
    rods = tuple(
        cylinder((60.0 * np.cos(a), 60.0 * np.sin(a), 0.0), (0, 0, 1), 6.0, 300.0, material="cortical", label=f"rod{i}")
        for i, a in enumerate(np.linspace(0, 2 * np.pi, 8, endpoint=False))
    )
    soft = phantom_background(Phantom("soft", (body,), np.zeros((0, 3)), D_MM, ""), g, surface)
    bony = phantom_background(Phantom("bony", (body,) + rods, np.zeros((0, 3)), D_MM, ""), g, surface)
    assert 0.7 * 0.1 < soft.random_noise_px(0.1) <= 0.1
    assert 0.025 <= bony.random_noise_px(0.1) < soft.random_noise_px(0.1)


def test_the_background_is_cached_by_the_views_content_and_the_cache_is_bounded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A second geometry object with the same views finds what the first computed; other views do not; the oldest
    BBs make way once :data:`calib.background.CACHED_BBS` are kept (nothing holds the geometries alive)."""
    import calib.background as background

    g = sawtooth(20, 128)
    bg = ObjectBackground.of(_body(70.0).line_integral, g, EllipticCylinder(70.0, 70.0, -40.0, 40.0), D_MM)
    xyz = spiral_markers(6, radius=70.0 + D_MM / 2)
    first = bg._computed(g, xyz, D_MM)
    n = len(bg._cache)
    again = bg._computed(ViewGeometry(g.vectors.copy(), g.panel), xyz, D_MM)
    assert len(bg._cache) == n and all(np.array_equal(a, b, equal_nan=True) for a, b in zip(first, again, strict=True))
    bg._computed(sawtooth(21, 128), xyz, D_MM)
    assert len(bg._cache) == n + 6
    monkeypatch.setattr(background, "CACHED_BBS", 8)
    bg._computed(sawtooth(22, 128), xyz, D_MM)
    assert len(bg._cache) == 8
