"""Resampling a volume onto another grid: linear functions exact, the same grid unchanged, zero outside."""

from __future__ import annotations

import numpy as np
import pytest

from orbitct.geometry import VolumeGrid
from recon.resample import resample_volume


def _linear(grid: VolumeGrid) -> np.ndarray:
    z, y, x = grid.coords_mm()
    return (0.5 * x[None, None, :] - 0.25 * y[None, :, None] + 0.125 * z[:, None, None] + 3.0).astype(np.float32)


def test_a_linear_volume_is_reproduced_exactly_on_a_finer_grid_inside_it() -> None:
    coarse = VolumeGrid.centered((10, 12, 14), 2.0, (1.0, -2.0, 0.5))
    fine = VolumeGrid.centered((13, 17, 19), (1.1, 1.2, 1.3), (1.0, -2.0, 0.5))  # within the coarse centres
    got = resample_volume(_linear(coarse), coarse, fine)
    assert got.shape == fine.shape and got.dtype == np.float32
    np.testing.assert_allclose(got, _linear(fine), rtol=0, atol=1e-4)


def test_the_same_grid_gives_the_same_volume() -> None:
    grid = VolumeGrid.centered((5, 6, 7), 0.5)
    vol = np.random.default_rng(0).random(grid.shape, dtype=np.float32)
    np.testing.assert_array_equal(resample_volume(vol, grid, grid), vol)


def test_outside_the_volume_is_zero_and_the_edge_fades_over_half_a_voxel() -> None:
    grid = VolumeGrid.centered((1, 1, 4), 1.0)  # x centres -1.5 .. 1.5
    onto = VolumeGrid((1, 1, 4), (0.5, 1.0, 1.0), (1.5, 0.0, 0.0))  # x at 1.5, 2.0, 2.5, 3.0
    got = resample_volume(np.ones(grid.shape, dtype=np.float32), grid, onto)
    np.testing.assert_allclose(got.ravel(), [1.0, 0.5, 0.0, 0.0])


def test_a_volume_that_does_not_match_its_grid_is_refused() -> None:
    with pytest.raises(ValueError, match="is not its grid's"):
        resample_volume(
            np.zeros((2, 2, 2), np.float32), VolumeGrid.centered((3, 3, 3), 1.0), VolumeGrid.centered((3, 3, 3), 1.0)
        )
