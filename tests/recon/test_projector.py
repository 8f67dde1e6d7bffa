"""Projector pair: exact adjoint on arbitrary geometries, agreement with analytic line integrals."""

from __future__ import annotations

import numpy as np
import pytest

from orbitct.geometry import ViewGeometry
from recon import FieldOfViewError, ReconError, VolumeGrid, check_fov, projector
from tests.helpers.recon import (
    SPHERES,
    bench_detector,
    sphere_line_integrals,
    voxelized_spheres,
)


def _assert_adjoint(A, x: np.ndarray, y: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """<A x, y> and <x, A^T y> agree to 1e-5 relative."""
    lhs = float(np.dot(A(x).ravel().astype(np.float64), y.ravel()))
    rhs = float(np.dot(x.ravel().astype(np.float64), A.T(y).ravel()))
    assert lhs > 0
    assert abs(lhs - rhs) / abs(lhs) < 1e-5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_adjoint_matches_forward_on_random_geometry(random_geometry: ViewGeometry, seed: int) -> None:
    rng = np.random.default_rng(seed)
    grid = VolumeGrid.centered((18, 22, 26), tuple(rng.uniform(0.7, 1.4, 3)), tuple(rng.normal(0, 2, 3)))
    A = projector(grid, random_geometry)
    x = rng.random(grid.shape).astype(np.float32)
    y = rng.random(A.proj_shape).astype(np.float32)
    _assert_adjoint(A, x, y)


def test_forward_of_voxelized_sphere_matches_analytic_line_integrals() -> None:
    det = bench_detector(64)
    g = ViewGeometry.from_carm(np.linspace(0, np.pi, 6), np.array([0, 0.3, -0.4, 0.1, 0.5, -0.2]), 785.0, 1200.0, det)
    grid = VolumeGrid.centered((64, 64, 64), 2.5)
    vol = voxelized_spheres(grid)
    sim = projector(grid, g)(vol)
    exact = sphere_line_integrals(g)
    inside = exact > 0.2 * exact.max()
    rel = np.abs(sim - exact)[inside] / exact[inside]
    assert np.median(rel) < 0.01
    assert np.sqrt(np.mean((sim - exact) ** 2)) < 0.01 * exact.max()


def test_operator_checks_shapes_and_geometry(random_geometry: ViewGeometry) -> None:
    grid = VolumeGrid.centered((8, 8, 8), 1.0)
    A = projector(grid, random_geometry)
    with pytest.raises(ReconError, match="expected shape"):
        A(np.zeros((8, 8, 9), np.float32))
    nan_views = ViewGeometry.empty_like(2, random_geometry.panel)
    with pytest.raises(ReconError, match="non-finite"):
        projector(grid, random_geometry.concatenate(nan_views))


def test_tap_offsets_are_exact_up_to_the_largest_volume_and_larger_ones_are_refused(
    random_geometry: ViewGeometry,
) -> None:
    from recon.projector import MAX_PADDED_VOXELS, _tap, _taps

    # a ray down the last rows of a padded 1625^3 volume: flat offsets from below 2^31 to just below 2^32
    side = 1625
    assert side**3 < MAX_PADDED_VOXELS
    n = 4
    idx = np.empty(n, np.int32)
    fa = np.empty(n, np.float32)
    fb = np.empty(n, np.float32)
    for b0 in (100.25, 800.25, side - 2.75):
        _taps(3.5, 0.25, b0, 0.0, side - 2 - n, n, 1, side, side * side, idx, fa, fb)
        want = [
            (side - 2 - n + j + 1) + int(3.5 + (side - 2 - n + j) * 0.25) * side + int(b0) * side**2 for j in range(n)
        ]
        assert [int(_tap(idx, j)) for j in range(n)] == want
    assert want[-1] > 2**31
    with pytest.raises(ReconError, match="too large for the CPU projector"):
        projector(VolumeGrid.centered((1700, 1700, 1700), 1.0), random_geometry)


def test_grid_far_from_views_is_rejected(random_geometry: ViewGeometry) -> None:
    check_fov(VolumeGrid.centered((10, 10, 10), 1.0), random_geometry)
    with pytest.raises(FieldOfViewError, match="misses the field of view"):
        check_fov(VolumeGrid.centered((10, 10, 10), 1.0, (900.0, 0.0, 0.0)), random_geometry)
    assert len(SPHERES) == 3


def test_adjoint_exact_for_axis_aligned_rays_at_the_volume_edge() -> None:
    """Views along the grid axes (zero slopes) and a grid whose faces the rays graze stay exact adjoints."""
    det = bench_detector(24)
    g = ViewGeometry.from_carm(np.array([0.0, np.pi / 2, np.pi, 1.5 * np.pi]), 0.0, 785.0, 1200.0, det)
    grid = VolumeGrid.centered((12, 16, 16), 427.0 / 24 * 785.0 / 1200.0)
    A = projector(grid, g)
    rng = np.random.default_rng(5)
    x = rng.random(grid.shape).astype(np.float32)
    y = rng.random(A.proj_shape).astype(np.float32)
    _assert_adjoint(A, x, y)


def test_operator_results_do_not_depend_on_threads_or_reused_buffers(random_geometry: ViewGeometry) -> None:
    import numba

    grid = VolumeGrid.centered((10, 12, 14), 1.1)
    A = projector(grid, random_geometry)
    rng = np.random.default_rng(3)
    x = rng.random(grid.shape).astype(np.float32)
    y = rng.random(A.proj_shape).astype(np.float32)
    fwd, back = A(x), A.T(y)
    np.testing.assert_array_equal(A(x), fwd)  # scratch buffers reused
    acc = np.ones(grid.shape, np.float32)
    np.testing.assert_allclose(A.back(y, out=acc), back + 1.0, rtol=1e-6)  # adds into out
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        A1 = projector(grid, random_geometry)
        np.testing.assert_allclose(A1(x), fwd, rtol=1e-6)
        np.testing.assert_allclose(A1.T(y), back, rtol=1e-5, atol=1e-6 * float(back.max()))
    finally:
        numba.set_num_threads(threads)


def _steep_and_random_views(random_geometry: ViewGeometry) -> ViewGeometry:
    """The random views plus views looking nearly along z (rays whose main axis is z)."""
    steep = ViewGeometry.from_carm(
        np.array([0.3, 2.0, 4.1]),
        np.array([1.45, -1.5, 1.2]),
        280.0,
        520.0,
        random_geometry.panel,
        shift=np.array([[0.0, 0.0, 2.0]] * 3),
    )
    return random_geometry.concatenate(steep)


def test_adjoint_equals_the_transpose_of_the_assembled_matrix(random_geometry: ViewGeometry) -> None:
    """Column by column assembly of A on a tiny grid: A.T(y) is A^T y voxel by voxel (every plane exactly once)."""
    g = _steep_and_random_views(random_geometry)
    grid = VolumeGrid.centered((5, 6, 7), (1.9, 1.7, 1.5), (0.4, -0.3, 0.2))
    A = projector(grid, g)
    cols = []
    e = np.zeros(grid.shape, np.float32)
    for j in range(e.size):
        e.flat[j] = 1.0
        cols.append(A(e).ravel().astype(np.float64))
        e.flat[j] = 0.0
    M = np.stack(cols, axis=1)
    y = np.random.default_rng(11).random(A.proj_shape).astype(np.float32)
    expected = (M.T @ y.ravel().astype(np.float64)).reshape(grid.shape)
    assert expected.max() > 0
    np.testing.assert_allclose(A.T(y), expected, rtol=1e-5, atol=1e-5 * expected.max())


def test_adjoint_does_not_depend_on_how_the_volume_is_cut_into_slabs(random_geometry: ViewGeometry) -> None:
    from recon.projector import joseph_adjoint, ray_slab_range, slab_bounds

    g = _steep_and_random_views(random_geometry)
    grid = VolumeGrid.centered((9, 11, 10), 1.3)
    A = projector(grid, g)
    y = np.random.default_rng(4).random(A.proj_shape).astype(np.float32)
    nz, ny, nx = grid.shape
    lo = np.empty(y.shape[0] * y.shape[1], np.int64)
    hi = np.empty_like(lo)
    ray_slab_range(A._rays, A._vox, nz, ny, nx, y.shape[1], y.shape[2], lo, hi)
    results = []
    for n_slabs in (1, 2, 3, 5, nz + 1, 100):
        acc = np.zeros(A.padded_shape, np.float32)
        bounds = slab_bounds(nz, n_slabs)
        assert bounds[0] == 0 and bounds[-1] == nz + 1 and np.all(np.diff(bounds) >= 1)
        joseph_adjoint(y, A._rays, A._vox, acc, bounds, lo, hi)
        results.append(acc[1:-1, 1:-1, 1:-1].copy())
    for r in results[1:]:
        np.testing.assert_allclose(r, results[0], rtol=1e-6, atol=1e-6 * float(results[0].max()))


def test_chunked_padded_calls_agree_with_whole_stack_calls(random_geometry: ViewGeometry) -> None:
    from recon.operator import pad_volume

    grid = VolumeGrid.centered((10, 12, 14), 1.1)
    A = projector(grid, random_geometry)
    rng = np.random.default_rng(8)
    x = rng.random(grid.shape).astype(np.float32)
    y = rng.random(A.proj_shape).astype(np.float32)
    xp = pad_volume(x)
    acc = np.zeros(A.padded_shape, np.float32)
    fwd = np.empty(A.proj_shape, np.float32)
    for i0 in range(0, A.proj_shape[0], 4):
        i1 = min(i0 + 4, A.proj_shape[0])
        A.forward_padded(xp, fwd[i0:i1], start=i0)
        A.back_padded(y[i0:i1], acc, start=i0)
    np.testing.assert_allclose(fwd, A(x), rtol=1e-6)
    back = A.T(y)
    np.testing.assert_allclose(acc[1:-1, 1:-1, 1:-1], back, rtol=1e-5, atol=1e-6 * float(back.max()))
    with pytest.raises(ReconError, match="views"):
        A.forward_padded(xp, np.empty((4,) + A.proj_shape[1:], np.float32), start=A.proj_shape[0] - 2)
    with pytest.raises(ReconError, match="padded volume"):
        A.forward_padded(x, fwd)
