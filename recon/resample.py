"""Resampling a volume onto another grid, so that two reconstructions can be compared voxel for voxel."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import VolumeGrid


def resample_volume(volume: NDArray[np.floating], grid: VolumeGrid, onto: VolumeGrid) -> NDArray[np.float32]:
    """``volume`` (on ``grid``) sampled at the voxel centres of ``onto``: trilinear between voxel centres, 0 outside
    the volume (half a voxel beyond its outer centres it fades to 0). Both grids are axis-aligned in the same frame
    (mm); the work is one 1-D interpolation per axis."""
    if tuple(volume.shape) != tuple(grid.shape):
        raise ValueError(f"the volume's shape {tuple(volume.shape)} is not its grid's {grid.shape}")
    out = np.asarray(volume, dtype=np.float32)
    for axis, (source, target) in enumerate(zip(grid.coords_mm(), onto.coords_mm(), strict=True)):
        out = _along(out, axis, (target - source[0]) / grid.voxel_mm[2 - axis])
    return out


def _along(values: NDArray[np.float32], axis: int, index: NDArray[np.float64]) -> NDArray[np.float32]:
    """``values`` linearly interpolated at fractional ``index`` along ``axis``; 0 beyond half a voxel outside."""
    n = values.shape[axis]
    padded = np.pad(values, [(1, 1) if a == axis else (0, 0) for a in range(values.ndim)])  # zeros just outside
    at = np.clip(index + 1.0, 0.0, n + 1.0)
    low = np.minimum(np.floor(at).astype(np.intp), n)
    weight = (at - low).astype(np.float32)
    shape = [1] * values.ndim
    shape[axis] = weight.size
    w = weight.reshape(shape)
    return np.take(padded, low, axis=axis) * (1 - w) + np.take(padded, low + 1, axis=axis) * w
