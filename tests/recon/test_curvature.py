"""PWLS's data curvature is computed once per views, geometry, grid and weights and reused from the cache by the
next run: the same image as recomputing it; anything it depends on changing means computing it again."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from orbitct.geometry import ViewGeometry
from recon import ReconError, VolumeGrid, projector, reconstruct_scan
from recon.curvature import cache_folder
from recon.pwls import pwls_sps
from tests.helpers.recon import bench_detector, write_sphere_scan

GRID = VolumeGrid.centered((16, 32, 32), 4.0)


@pytest.fixture(autouse=True)
def _own_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ORBITCT_CACHE_DIR", str(tmp_path / "cache"))


def _scan(path: Path, seed: int = 0) -> Path:
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    write_sphere_scan(
        path, ViewGeometry.from_carm(t, 0.2 * np.sin(2 * t), 785.0, 1200.0, bench_detector(40)), seed=seed
    )
    return path


def test_the_second_run_reuses_the_curvature_and_gives_the_same_image(tmp_path: Path) -> None:
    scan = _scan(tmp_path / "a.h5")
    kwargs = {"algorithm": "pwls", "geometry": "nominal", "grid": GRID, "iterations": 2, "subsets": 4, "momentum": True}
    first = reconstruct_scan(scan, name="first", **kwargs)
    assert first.params["curvature"] == "computed" and len(list(cache_folder().glob("*.npy"))) == 1
    again = reconstruct_scan(scan, name="again", beta=0.01, **kwargs)
    assert again.params["curvature"] == "reused"
    np.testing.assert_array_equal(again.volume, first.volume)
    streamed = reconstruct_scan(scan, name="streamed", stream="file", **kwargs)  # the same weights, read from the file
    assert streamed.params["curvature"] == "reused"
    np.testing.assert_allclose(streamed.volume, first.volume, rtol=1e-5, atol=1e-6 * float(first.volume.max()))


def test_what_the_curvature_depends_on_changing_means_computing_it_again(tmp_path: Path) -> None:
    scan = _scan(tmp_path / "a.h5")
    kwargs = {"algorithm": "pwls", "geometry": "nominal", "iterations": 1}
    assert reconstruct_scan(scan, name="a", grid=GRID, **kwargs).params["curvature"] == "computed"
    other_grid = VolumeGrid.centered((16, 32, 32), 3.5)
    assert reconstruct_scan(scan, name="b", grid=other_grid, **kwargs).params["curvature"] == "computed"
    other_data = _scan(tmp_path / "b.h5", seed=1)  # the same views and grid, other counts: other weights
    assert reconstruct_scan(other_data, name="a", grid=GRID, **kwargs).params["curvature"] == "computed"
    for path in cache_folder().glob("*.npy"):
        path.write_bytes(b"damaged")  # a cache that cannot be read is computed again, never trusted
    assert reconstruct_scan(scan, name="c", grid=GRID, **kwargs).params["curvature"] == "computed"
    assert reconstruct_scan(scan, name="d", grid=GRID, **kwargs).params["curvature"] == "reused"


def test_a_given_curvature_of_the_wrong_shape_is_refused() -> None:
    t = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    A = projector(GRID, ViewGeometry.from_carm(t, 0 * t, 785.0, 1200.0, bench_detector(16)))
    y = np.zeros(A.proj_shape, np.float32)
    with pytest.raises(ReconError, match="data_curvature: expected float32 of shape"):
        pwls_sps(A, y, iterations=1, data_curvature=np.ones((2, 2, 2), np.float32))
