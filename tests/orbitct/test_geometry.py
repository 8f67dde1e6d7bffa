"""Shared geometry: matrices <-> vectors, projection, constructors, errors."""

import numpy as np
import pytest

from orbitct.geometry import GeometryError, Panel, ViewGeometry, ideal_bench_pose
from orbitct.rotations import rotvec_to_matrix

DET = Panel(96, 128, 0.8, 0.7)


def random_views(n: int = 25, seed: int = 0) -> ViewGeometry:
    rng = np.random.default_rng(seed)
    return ViewGeometry.from_carm(
        rng.uniform(-np.pi, np.pi, n),
        rng.uniform(-0.6, 0.6, n),
        rng.uniform(600, 900, n),
        rng.uniform(1100, 1400, n),
        DET,
        du=rng.uniform(-20, 20, n),
        dv=rng.uniform(-20, 20, n),
        eta=rng.uniform(-0.1, 0.1, n),
        shift=rng.uniform(-10, 10, (n, 3)),
    )


def test_vectors_matrices_round_trip() -> None:
    g = random_views()
    back = ViewGeometry.from_matrices(g.matrices, DET)
    assert np.allclose(back.vectors, g.vectors, rtol=1e-9, atol=1e-9 * np.abs(g.vectors).max())
    # any scale (also negative) of the matrices gives the same views
    back2 = ViewGeometry.from_matrices(-3.7 * g.matrices, DET)
    assert back2.allclose(g, atol_mm=1e-9 * 1500)


def test_matrix_w_is_depth() -> None:
    g = random_views(5)
    pts = np.random.default_rng(1).uniform(-50, 50, (7, 3))
    _, w = g.project_with_depth(pts)
    depth = np.einsum("nkj,nj->nk", pts[None] - g.S[:, None], g.normal)
    assert np.allclose(w, depth, rtol=1e-9)


def test_point_projects_where_source_ray_meets_detector_plane() -> None:
    g = random_views(10, seed=2)
    pts = np.random.default_rng(3).uniform(-80, 80, (12, 3))
    uv = g.project(pts)
    for n in range(g.n_views):
        S, D, nrm = g.S[n], g.D[n], g.normal[n]
        for k, p in enumerate(pts):
            d = p - S
            hit = S + d * ((D - S) @ nrm) / (d @ nrm)
            c0, r0 = DET.center
            expect = D + (uv[n, k, 0] - c0) * g.u[n] + (uv[n, k, 1] - r0) * g.v[n]
            assert np.allclose(hit, expect, atol=1e-8)


def test_backproject_inverts_project() -> None:
    g = random_views(4, seed=5)
    pts = np.random.default_rng(6).uniform(-60, 60, (9, 3))
    uv = g.project(pts)
    o, d = g.backproject(uv)
    # distance from each point to its back-projected ray is zero
    v = pts[None] - o
    dist = np.linalg.norm(v - np.einsum("nki,nki->nk", v, d)[..., None] * d, axis=-1)
    assert dist.max() < 1e-8


def test_reference_view_orientation() -> None:
    g = ViewGeometry.from_carm(0.0, 0.0, 785.0, 1200.0, DET)
    assert np.allclose(g.S[0], [0, -785, 0]) and np.allclose(g.D[0], [0, 415, 0])
    assert np.allclose(g.u[0], [0.8, 0, 0]) and np.allclose(g.v[0], [0, 0, -0.7])
    # positive tilt moves the source towards +z; theta turns it about +z
    assert ViewGeometry.from_carm(0.0, 0.3, 785.0, 1200.0, DET).S[0, 2] > 0
    assert ViewGeometry.from_carm(0.3, 0.0, 785.0, 1200.0, DET).S[0, 0] > 0


def test_object_poses_match_carm() -> None:
    rng = np.random.default_rng(7)
    th, ph = rng.uniform(-3, 3, 20), rng.uniform(-0.5, 0.5, 20)
    lab = ViewGeometry.from_carm(0.0, 0.0, 785.0, 1200.0, DET)
    a = ViewGeometry.from_object_poses(lab, ideal_bench_pose(th, ph), np.zeros(3))
    b = ViewGeometry.from_carm(th, ph, 785.0, 1200.0, DET)
    assert a.allclose(b, atol_mm=1e-9)


def test_transformed_moves_projections_consistently() -> None:
    g = random_views(6, seed=8)
    R = rotvec_to_matrix([0.1, -0.2, 0.3])
    t = np.array([5.0, -3.0, 2.0])
    pts = np.random.default_rng(9).uniform(-40, 40, (5, 3))
    assert np.allclose(g.transformed(R, t).project(pts @ R.T + t), g.project(pts), atol=1e-9)


def test_projected_size_is_what_a_small_object_at_the_isocenter_spans() -> None:
    g = random_views(6, seed=4)
    size_px = g.projected_size_px(2.0)
    # two points 1 mm either side of the origin, across the beam along the panel's columns: their projections lie
    # size_px apart (the panel's mean pitch: the columns' and rows' pitches differ here, so along u by their ratio)
    across = g.u / np.linalg.norm(g.u, axis=1, keepdims=True)
    for n in range(g.n_views):
        uv = g[n : n + 1].project(np.array([-across[n], across[n]]))[0]
        along_u_px = abs(uv[1, 0] - uv[0, 0]) * DET.pitch_col / np.sqrt(DET.pitch_col * DET.pitch_row)
        assert along_u_px == pytest.approx(size_px[n], rel=2e-3)


def test_slicing_and_nan_views() -> None:
    g = random_views(10)
    assert g[2:5].n_views == 3 and g[3].n_views == 1
    assert np.array_equal(g[[1, 4]].vectors, g.vectors[[1, 4]])
    e = ViewGeometry.empty_like(3, DET)
    assert not e.valid.any() and np.isnan(e.matrices).all()
    assert "NaN" in repr(e) and "n_views=10" in repr(g)


@pytest.mark.parametrize(
    "call, expected",
    [
        (lambda: ViewGeometry(np.zeros((3, 11)), DET), "expected shape (N, 12), got (3, 11)"),
        (lambda: ViewGeometry.from_matrices(np.zeros((2, 3, 3)), DET), "expected shape (N, 3, 4), got (2, 3, 3)"),
        (lambda: random_views(3).project(np.zeros((4, 2))), "expected shape (K, 3) or (N, K, 3), got (4, 2)"),
        (lambda: Panel(0, 5, 1, 1), "rows and cols must be >= 1"),
        (lambda: ViewGeometry.from_carm(0, 0, 900, 800, DET), "sdd must exceed sad"),
    ],
)
def test_wrong_shapes_say_expected_and_got(call, expected: str) -> None:
    with pytest.raises(GeometryError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        call()
