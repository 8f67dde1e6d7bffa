"""Metal artifact reduction reduces streaks around metal."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from orbitct.geometry import ViewGeometry
from recon import VolumeGrid, reconstruct_scan, rmse
from recon.mar import fill_traces
from tests.helpers.recon import (
    SPHERES,
    bench_detector,
    voxelized_spheres,
    write_sphere_scan,
)

METAL = [((15.0, -20.0, 0.0), 3.0, 0.78), ((-20.0, 15.0, 2.0), 2.5, 0.78)]  # steel beads
SHAPE, VOXEL = (24, 64, 64), 2.0


def test_fill_traces_interpolates_along_rows() -> None:
    li = np.tile(np.arange(10, dtype=np.float32), (1, 2, 1))
    li[0, :, 4:7] = 50.0
    mask = li > 20
    out = fill_traces(li, mask)
    assert np.allclose(out[0, 0], np.arange(10)) and li[0, 0, 5] == 50.0


@pytest.fixture(scope="module")
def metal_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    g = ViewGeometry.from_carm(np.linspace(0, 2 * np.pi, 72, endpoint=False), 0.0, 785.0, 1200.0, bench_detector(80))
    path = tmp_path_factory.mktemp("mar") / "metal.h5"
    write_sphere_scan(path, g, spheres=SPHERES + METAL, i0=2e4)
    return path


def _streak_region(grid: VolumeGrid) -> np.ndarray:
    z, y, x = grid.coords_mm()
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    near = np.zeros(grid.shape, bool)
    core = np.zeros(grid.shape, bool)
    for c, r, _ in METAL:
        dist = np.sqrt((xx - c[0]) ** 2 + (yy - c[1]) ** 2 + (zz - c[2]) ** 2)
        near |= dist < 25.0
        core |= dist < r + 4.0
    return near & ~core


@pytest.mark.parametrize("algorithm", ["fdk", pytest.param("pwls", marks=pytest.mark.slow)])
def test_mar_reduces_streak_error_and_keeps_metal(metal_scan: Path, algorithm: str) -> None:
    grid = VolumeGrid.centered(SHAPE, VOXEL)
    truth = voxelized_spheres(grid, SPHERES + METAL)
    ring = _streak_region(grid)
    kw = dict(algorithm=algorithm, geometry="nominal", voxel_mm=VOXEL, shape=SHAPE, iterations=8)
    plain = reconstruct_scan(metal_scan, **kw)
    fixed = reconstruct_scan(metal_scan, mar=True, **kw)
    assert fixed.name == f"{algorithm}_nominal_mar" and fixed.params["metal_voxels"] > 0
    assert rmse(fixed.volume, truth, ring) < 0.85 * rmse(plain.volume, truth, ring)
    assert fixed.volume.max() >= 0.9 * plain.volume.max()  # the metal is back in the volume


def test_threshold_segmentation_finds_small_dense_spots_only() -> None:
    from recon.mar import traces_by_threshold

    rr, cc = np.mgrid[0:40, 0:40]
    li = (2.0 * np.exp(-((rr - 20) ** 2 + (cc - 20) ** 2) / 300.0)).astype(np.float32)[None]  # broad body
    li[0, 10:12, 30:32] += 1.5  # a bead
    mask = traces_by_threshold(li, 0.5, size_px=7, dilate=0)
    assert mask[0, 10:12, 30:32].all() and mask.sum() == 4
