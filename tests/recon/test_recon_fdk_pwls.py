"""FDK accuracy on circular scans (full and short) and PWLS/SPS behaviour."""

from __future__ import annotations

import numpy as np
import pytest

from recon_helpers import bench_detector, sphere_line_integrals, voxelized_spheres
from orbitct.geometry import ViewGeometry
from recon import ReconError, VolumeGrid, projector
from recon.fdk import WINDOWS, fdk, ramp_filter, redundancy_weights
from recon.pwls import pwls_sps

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
    res = pwls_sps(projector(GRID, g), y, w, iterations=12, x0=x0)
    cost = np.asarray(res.cost)
    assert cost.size == 13
    assert np.all(np.diff(cost) <= 1e-6 * cost[0])
    assert cost[-1] < 0.9 * cost[0]
    assert res.volume.min() >= 0
    assert _rmse(res.volume, truth) < _rmse(x0, truth)


def test_pwls_second_order_and_ordered_subsets(sawtooth_data) -> None:
    g, y, w = sawtooth_data
    A = projector(GRID, g)
    res = pwls_sps(A, y, w, iterations=3, neighbourhood=2, subsets=5)
    assert len(res.cost) == 4 and res.cost[-1] < res.cost[0]
    with pytest.raises(ReconError, match="neighbourhood"):
        pwls_sps(A, y, w, iterations=1, neighbourhood=3)
