"""Image quality: RMSE against a voxelized phantom, FWHM of a wire's point-spread function."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from orbitct.geometry import VolumeGrid
from recon.errors import ReconError


def reference_volume(phantom: Any, grid: VolumeGrid, supersample: int = 3) -> NDArray[np.float32]:
    """The phantom voxelized on ``grid`` (``orbitct.phantoms.voxelize``, partial-volume averaged)."""
    from orbitct.phantoms import Phantom, voxelize

    if isinstance(phantom, dict):
        phantom = Phantom.from_json(phantom)
    return voxelize(
        phantom, shape=grid.shape, voxel_mm=grid.voxel_mm, origin_mm=grid.origin_mm, supersample=supersample
    )


def rmse(
    volume: NDArray[np.floating[Any]], reference: NDArray[np.floating[Any]], mask: NDArray[np.bool_] | None = None
) -> float:
    """Root-mean-square difference (1/mm), optionally inside ``mask``."""
    if volume.shape != reference.shape:
        raise ReconError(f"volume {volume.shape} and reference {reference.shape} differ in shape")
    d = np.asarray(volume, dtype=np.float64) - reference
    if mask is not None:
        d = d[mask]
    return float(np.sqrt(np.mean(d**2)))


def fov_mask(
    grid: VolumeGrid, radius_mm: float, half_height_mm: float, center_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> NDArray[np.bool_]:
    """Voxels inside a z-cylinder (where every view sees the object)."""
    z, y, x = grid.coords_mm()
    zz, yy, xx = np.meshgrid(z - center_mm[2], y - center_mm[1], x - center_mm[0], indexing="ij")
    return (xx**2 + yy**2 <= radius_mm**2) & (np.abs(zz) <= half_height_mm)


def _half_max_width(profile: NDArray[np.float64], step: float) -> float:
    peak = int(np.argmax(profile))
    edge = max(1, profile.size // 6)
    tails = np.concatenate([profile[:edge], profile[-edge:]])
    base = float(np.median(tails))
    half = base + (profile[peak] - base) / 2
    if profile[peak] - base <= 5 * float(np.std(tails)) + 1e-6 * abs(base):
        return float("nan")  # no peak above the background noise
    i = peak
    while i > 0 and profile[i] > half:
        i -= 1
    j = peak
    while j < profile.size - 1 and profile[j] > half:
        j += 1
    if profile[i] > half or profile[j] > half:
        return float("nan")  # never drops to half maximum: too diffuse to measure
    left = i + (half - profile[i]) / (profile[i + 1] - profile[i])
    right = j - (half - profile[j]) / (profile[j - 1] - profile[j])
    return float((right - left) * step)


def wire_fwhm(
    volume: NDArray[np.floating[Any]],
    grid: VolumeGrid,
    *,
    axis: str = "z",
    center_mm: tuple[float, float] | None = None,
    search_mm: float = 10.0,
    slices: slice | None = None,
    upsample: int = 10,
) -> dict[str, float]:
    """FWHM (mm) of a thin wire's in-plane PSF; the wire runs along ``axis`` ('z', 'y' or 'x').

    Slices across the wire are averaged, the peak is searched within ``search_mm`` of
    ``center_mm`` (default the grid centre), and profiles through it are measured both ways.
    Returns ``fwhm_mm`` (mean), ``fwhm_a_mm``, ``fwhm_b_mm`` and the peak position; NaN if too diffuse.
    """
    ax = {"z": 0, "y": 1, "x": 2}.get(axis)
    if ax is None:
        raise ReconError(f"wire axis must be 'x', 'y' or 'z', got {axis!r}")
    vol = np.moveaxis(np.asarray(volume, dtype=np.float64), ax, 0)
    if slices is not None:
        vol = vol[slices]
    img = vol.mean(axis=0)
    coords = grid.coords_mm()  # (z, y, x)
    in_plane = [coords[i] for i in range(3) if i != ax]
    steps = [grid.voxel_mm[2 - i] for i in range(3) if i != ax]
    c = [float(np.mean(a)) for a in in_plane] if center_mm is None else list(center_mm)
    ia = np.abs(in_plane[0] - c[0]) <= search_mm
    ib = np.abs(in_plane[1] - c[1]) <= search_mm
    sub = np.where(ia[:, None] & ib[None, :], img, -np.inf)
    pa, pb = np.unravel_index(int(np.argmax(sub)), img.shape)
    half = int(np.ceil(search_mm / min(steps)))
    t = np.arange(-half * upsample, half * upsample + 1) / upsample
    prof_a = ndimage.map_coordinates(img, [pa + t, np.full_like(t, pb)], order=3, mode="nearest")
    prof_b = ndimage.map_coordinates(img, [np.full_like(t, pa), pb + t], order=3, mode="nearest")
    fa = _half_max_width(prof_a, steps[0] / upsample)
    fb = _half_max_width(prof_b, steps[1] / upsample)
    return {
        "fwhm_mm": float(np.mean([fa, fb])),
        "fwhm_a_mm": fa,
        "fwhm_b_mm": fb,
        "peak_a_mm": float(in_plane[0][pa]),
        "peak_b_mm": float(in_plane[1][pb]),
    }
