"""The grid fitted to the object: found in a coarse reconstruction, so that voxels hold the object, not air."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import Panel, ViewGeometry, VolumeGrid
from recon.fdk import fdk
from recon.grid import fov_radius_height

COARSE_PX = 128  # the coarse FDK that finds the object bins the panel to about this many pixels a side
OBJECT_MARGIN_MM = 5.0


def _bin_factor(rows: int, cols: int) -> int:
    """The largest factor up to ``max(rows, cols) / COARSE_PX`` (rounded up) that divides both (1 if none)."""
    top = max(1, int(np.ceil(max(rows, cols) / COARSE_PX)))
    return next(b for b in range(top, 0, -1) if rows % b == 0 and cols % b == 0)


def _otsu(values: NDArray[np.float32], bins: int = 256) -> float:
    """The threshold that best separates ``values`` into two classes (Otsu), over their 0.1-99.9 percentile range."""
    lo, hi = np.percentile(values, [0.1, 99.9])
    hist, edges = np.histogram(np.clip(values, lo, hi), bins=bins, range=(lo, hi))
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    mean0 = m0 / np.maximum(w0, 1)
    mean1 = (m0[-1] - m0) / np.maximum(w1, 1)
    return float(centres[int(np.argmax(w0 * w1 * (mean0 - mean1) ** 2))])


def object_grid(
    stack: Any,
    geometry: ViewGeometry,
    fov: VolumeGrid,
    *,
    margin_mm: float = OBJECT_MARGIN_MM,
    min_part: float = 0.05,
    chunk: int = 16,
) -> tuple[VolumeGrid, str]:
    """The part of the field-of-view grid ``fov`` that holds the object (same voxel size), and a line saying so.

    A coarse FDK (panel binned to about COARSE_PX pixels, voxels as coarse), inside the cylinder every view sees,
    is split into object and air by Otsu's threshold; pieces smaller than ``min_part`` of the largest are noise.
    The box around the rest, widened by ``margin_mm`` and a coarse voxel and kept inside the field of view, is
    the grid. Where nothing stands out (an empty scan), the whole field of view is kept."""
    import scipy.ndimage

    det = geometry.panel
    b = _bin_factor(det.rows, det.cols)
    rows, cols = det.rows // b, det.cols // b
    coarse_geometry = geometry.with_panel(Panel(rows, cols, det.pitch_col * b, det.pitch_row * b))
    n = stack.shape[0]
    binned = np.empty((n, rows, cols), np.float32)
    for i in range(0, n, chunk):
        part = np.asarray(stack[i : i + chunk], dtype=np.float32)
        binned[i : i + part.shape[0]] = part.reshape(part.shape[0], rows, b, cols, b).mean(axis=(2, 4))
    voxel = fov.voxel_mm[0]
    coarse_voxel = voxel * b
    ext = fov.extent_mm  # rows x, y, z: (low, high)
    nz, ny, nx = (max(1, int(np.ceil((ext[k, 1] - ext[k, 0]) / coarse_voxel))) for k in (2, 1, 0))
    cx, cy, cz = (float(c) for c in ext.mean(axis=1))
    coarse = VolumeGrid.centered((nz, ny, nx), coarse_voxel, (cx, cy, cz))
    volume = fdk(binned, coarse, coarse_geometry, window="hann")
    z, y, x = coarse.coords_mm()
    radius, height, center = fov_radius_height(geometry)
    # only the cylinder every view sees: outside it a reconstruction is streaks, not object
    seen = (
        ((x[None, None, :] - center[0]) ** 2 + (y[None, :, None] - center[1]) ** 2 <= (radius - coarse_voxel) ** 2)
        & (np.abs(z[:, None, None] - center[2]) <= 0.5 * height - coarse_voxel)
        & np.isfinite(volume)
    )
    keep_all = (fov, f"the whole field of view ({_describe(fov)}): no object stands out in a coarse reconstruction")
    if seen.sum() < 64:
        return keep_all
    mask = scipy.ndimage.binary_opening((volume > _otsu(volume[seen])) & seen, iterations=1)
    labels, count = scipy.ndimage.label(mask)
    if count == 0:
        return keep_all
    sizes = np.bincount(labels.ravel())[1:]
    mask = np.isin(labels, 1 + np.flatnonzero(sizes >= min_part * sizes.max()))
    idx = [np.flatnonzero(mask.any(axis=axes)) for axes in ((0, 1), (0, 2), (1, 2))]  # x, y, z voxels holding object
    pad = margin_mm + coarse_voxel
    lo = np.array([x[idx[0][0]], y[idx[1][0]], z[idx[2][0]]]) - pad
    hi = np.array([x[idx[0][-1]], y[idx[1][-1]], z[idx[2][-1]]]) + pad
    lo, hi = np.maximum(lo, ext[:, 0]), np.minimum(hi, ext[:, 1])
    nz, ny, nx = (
        max(4, min(int(np.ceil((hi[k] - lo[k]) / voxel)), s)) for k, s in zip((2, 1, 0), fov.shape, strict=True)
    )
    cx, cy, cz = (float(c) for c in 0.5 * (lo + hi))
    grid = VolumeGrid.centered((nz, ny, nx), voxel, (cx, cy, cz))
    share = 100.0 * np.prod(grid.shape) / np.prod(fov.shape)
    return grid, (
        f"fitted to the object: {_describe(grid)}, {share:.0f} % of the field of view's voxels (from a coarse "
        f"reconstruction at {coarse_voxel:.1f} mm; --grid fov for the whole field of view, --shape for your own)"
    )


def _describe(grid: VolumeGrid) -> str:
    ext = grid.extent_mm
    nz, ny, nx = grid.shape
    return (
        f"{nz}x{ny}x{nx} voxels of {grid.voxel_mm[0]:g} mm, x {ext[0, 0]:.0f}..{ext[0, 1]:.0f}, "
        f"y {ext[1, 0]:.0f}..{ext[1, 1]:.0f}, z {ext[2, 0]:.0f}..{ext[2, 1]:.0f} mm"
    )
