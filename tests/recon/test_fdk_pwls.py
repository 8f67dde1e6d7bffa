"""FDK accuracy on circular scans (full and short) and PWLS/SPS behaviour."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from orbitct.geometry import ViewGeometry
from recon import ReconError, VolumeGrid, projector
from recon.fdk import WINDOWS, fdk, ramp_filter, redundancy_weights
from recon.pwls import pwls_sps
from tests.helpers.recon import bench_detector, sphere_line_integrals, voxelized_spheres

GRID = VolumeGrid.centered((40, 64, 64), 2.0)


def _rmse(vol: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean((vol - truth)[8:32] ** 2)))  # central slabs (cone-beam data complete)


@pytest.fixture(scope="module")
def truth() -> np.ndarray:
    return voxelized_spheres(GRID)


@pytest.mark.parametrize("arc, scheme", [(2 * np.pi, "azimuth increments"), (np.pi + 0.6, "parker")])
def test_fdk_circular_scan_reaches_rmse(truth: np.ndarray, arc: float, scheme: str) -> None:
    g = ViewGeometry.from_carm(np.linspace(0, arc, 90, endpoint=False) + 0.3, 0.0, 785.0, 1200.0, bench_detector(80))
    assert redundancy_weights(g)[2] == scheme
    vol = fdk(sphere_line_integrals(g), GRID, g, window="hann")
    # stated accuracy: RMSE below 15 % of the water-like background (0.02 /mm)
    assert _rmse(vol, truth) < 0.003
    assert abs(float(np.median(vol[20, 24:40, 24:40])) - 0.02) < 0.001


def test_ramp_windows_are_known_and_roll_off() -> None:
    for w in WINDOWS:
        H = ramp_filter(64, w)
        assert H[0] >= 0 and H[H.size // 4] > 0
    assert ramp_filter(64, "hann")[-1] < 1e-6 < ramp_filter(64, "ram-lak")[-1]
    with pytest.raises(ReconError, match="choose one of"):
        ramp_filter(64, "gauss")


@pytest.fixture(scope="module")
def sawtooth_data():
    n = 60
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    g = ViewGeometry.from_carm(t, 0.35 * np.sin(2 * t), 785.0, 1200.0, bench_detector(72))
    rng = np.random.default_rng(3)
    counts = rng.poisson(2e4 * np.exp(-sphere_line_integrals(g))).astype(np.float32)
    y = -np.log(np.maximum(counts, 1) / 2e4).astype(np.float32)
    return g, y, (counts / 2e4).astype(np.float32)


@pytest.mark.slow
def test_pwls_cost_decreases_monotonically_and_beats_fdk(sawtooth_data, truth: np.ndarray) -> None:
    g, y, w = sawtooth_data
    x0 = fdk(y, GRID, g, window="hann")
    res = pwls_sps(projector(GRID, g), y, w, iterations=12, x0=x0, final_cost=True)
    cost = np.asarray(res.cost)
    assert cost.size == 13 and res.final_cost
    assert np.all(np.diff(cost) <= 1e-6 * cost[0])
    assert cost[-1] < 0.9 * cost[0]
    assert res.volume.min() >= 0
    assert _rmse(res.volume, truth) < _rmse(x0, truth)


def test_the_final_cost_is_one_more_pass_that_changes_nothing_else(sawtooth_data) -> None:
    """Without ``final_cost`` the run skips the forward projection made only to report the result's cost: the same
    image (also with momentum, whose result is the iterate, not the extrapolated point) and the same earlier costs."""
    g, y, w = sawtooth_data
    A = projector(GRID, g)
    counted = _CountingProjector(A)
    for kwargs in ({}, {"subsets": 4, "momentum": True}):
        with_final = pwls_sps(A, y, w, iterations=3, final_cost=True, **kwargs)
        counted.views = 0
        without = pwls_sps(counted, y, w, iterations=3, **kwargs)  # type: ignore[arg-type]
        np.testing.assert_array_equal(without.volume, with_final.volume)
        np.testing.assert_array_equal(without.cost, with_final.cost[:-1])
        n_views = A.proj_shape[0]
        assert counted.views == (1 + 3) * n_views  # the curvature's pass and one per iteration, no final pass


class _CountingProjector:
    """A projector that counts the views it forward-projects (everything else is the projector's)."""

    def __init__(self, A: Any) -> None:
        self._A, self.views = A, 0

    def __getattr__(self, name: str) -> Any:
        return getattr(self._A, name)

    def subset(self, views: Any) -> Any:
        counted = _CountingProjector(self._A.subset(views))
        counted._parent = self  # type: ignore[attr-defined]
        return counted

    def forward_padded(self, xp: Any, out: Any, j0: int) -> Any:
        parent = getattr(self, "_parent", self)
        parent.views += out.shape[0]
        return self._A.forward_padded(xp, out, j0)


def test_pwls_second_order_and_ordered_subsets(sawtooth_data) -> None:
    g, y, w = sawtooth_data
    A = projector(GRID, g)
    res = pwls_sps(A, y, w, iterations=3, neighbourhood=2, subsets=5)
    assert len(res.cost) == 3 and res.cost[-1] < res.cost[0] and not res.final_cost  # the iterates before the result
    with pytest.raises(ReconError, match="neighbourhood"):
        pwls_sps(A, y, w, iterations=1, neighbourhood=3)


def test_pwls_streams_projections_from_an_hdf5_file(sawtooth_data, tmp_path) -> None:
    """Projections and weights read chunk by chunk from datasets give the in-memory result, for any chunk size."""
    import h5py

    g, y, w = sawtooth_data
    A = projector(GRID, g)
    x0 = fdk(y, GRID, g, window="hann")
    ref = pwls_sps(A, y, w, iterations=3, x0=x0)
    with h5py.File(tmp_path / "data.h5", "w") as f:
        f["y"], f["w"] = y, w
    with h5py.File(tmp_path / "data.h5", "r") as f:
        for chunk in (1, 7, 1000):
            res = pwls_sps(A, f["y"], f["w"], iterations=3, x0=x0, chunk_views=chunk)
            np.testing.assert_allclose(res.cost, ref.cost, rtol=1e-4)
            np.testing.assert_allclose(res.volume, ref.volume, rtol=1e-4, atol=1e-5 * float(ref.volume.max()))
        sub = pwls_sps(A, f["y"], f["w"], iterations=2, x0=x0, subsets=4, chunk_views=3)
        np.testing.assert_allclose(
            sub.volume,
            pwls_sps(A, y, w, iterations=2, x0=x0, subsets=4).volume,
            rtol=1e-4,
            atol=1e-5 * float(ref.volume.max()),
        )
    with pytest.raises(ReconError, match="chunk_views"):
        pwls_sps(A, y, w, iterations=1, chunk_views=0)
    with pytest.raises(ReconError, match="x0"):
        pwls_sps(A, y, w, iterations=1, x0=x0[:-1])


def test_pwls_updates_a_padded_start_in_place(sawtooth_data) -> None:
    """FDK written into a padded volume's interior starts PWLS without a second volume; same result."""
    g, y, w = sawtooth_data
    A = projector(GRID, g)
    x0 = fdk(y, GRID, g, window="hann")
    ref = pwls_sps(A, y, w, iterations=2, x0=x0)
    xp = np.full(A.padded_shape, 7.0, np.float32)  # the border is cleared by the solver
    fdk(y, GRID, g, window="hann", out=xp[1:-1, 1:-1, 1:-1])
    np.testing.assert_allclose(xp[1:-1, 1:-1, 1:-1], x0, rtol=1e-6, atol=1e-7)
    res = pwls_sps(A, y, w, iterations=2, x0=xp)
    assert np.shares_memory(res.volume, xp)
    np.testing.assert_allclose(res.volume, ref.volume, rtol=1e-5, atol=1e-6 * float(ref.volume.max()))
    with pytest.raises(ReconError, match="x0"):
        pwls_sps(A, y, w, iterations=1, x0=np.zeros((3, 3, 3), np.float32))
    with pytest.raises(ReconError, match="in place"):
        pwls_sps(A, y, w, iterations=1, x0=np.zeros(A.padded_shape, np.float64))
    with pytest.raises(ReconError, match="out"):
        fdk(y, GRID, g, out=np.zeros((2, 2, 2), np.float32))


@pytest.mark.slow
def test_os_momentum_gets_further_in_few_passes_and_agrees_with_the_minimiser(sawtooth_data) -> None:
    g, y, w = sawtooth_data
    A = projector(GRID, g)
    seen: list[int] = []
    mom = pwls_sps(
        A, y, w, iterations=8, subsets=6, momentum=True, final_cost=True, callback=lambda k, x: seen.append(k)
    )
    plain_os = pwls_sps(A, y, w, iterations=8, subsets=6, final_cost=True)
    sps = pwls_sps(A, y, w, iterations=8, final_cost=True)
    assert seen == list(range(1, 9))
    assert mom.cost[-1] < plain_os.cost[-1] < sps.cost[-1]  # the final cost is exact, at each result
    assert mom.volume.min() >= 0  # the result is the iterate, not the extrapolated point
    # the same minimiser: many SPS iterations from the momentum result change little, and cost no less
    polished = pwls_sps(A, y, w, iterations=40, x0=mom.volume, final_cost=True)
    assert polished.cost[-1] <= mom.cost[-1]
    assert (mom.cost[-1] - polished.cost[-1]) < 0.02 * (sps.cost[0] - polished.cost[-1])
