"""Metal artifact reduction: segment metal traces, fill them by interpolation, reconstruct, add metal back."""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray
from scipy import ndimage

from recon.errors import ReconError
from recon.operator import Projector

METHODS = ("threshold", "reprojection")


def metal_in_volume(volume: NDArray[np.float32], metal_mu: float, dilate: int = 1) -> NDArray[np.bool_]:
    """Voxels above ``metal_mu`` (1/mm), grown by ``dilate`` voxels."""
    mask = volume > metal_mu
    if dilate and mask.any():
        mask = ndimage.binary_dilation(mask, iterations=dilate)
    return mask


def traces_by_threshold(
    li: NDArray[np.float32], threshold: float, size_px: int = 9, dilate: int = 1
) -> NDArray[np.bool_]:
    """Metal traces: line integrals that exceed their local background (grey opening) by ``threshold``."""
    out = np.zeros(li.shape, dtype=bool)
    for n in range(li.shape[0]):
        tophat = li[n] - ndimage.grey_opening(li[n], size=(size_px, size_px))
        m = tophat > threshold
        if dilate and m.any():
            m = ndimage.binary_dilation(m, iterations=dilate)
        out[n] = m
    return out


def traces_by_reprojection(A: Projector, metal: NDArray[np.bool_], min_length_mm: float = 0.05) -> NDArray[np.bool_]:
    """Metal traces: pixels whose rays cross the metal voxels for more than ``min_length_mm``."""
    return A(metal.astype(np.float32)) > min_length_mm


@njit(parallel=True, cache=True)
def _fill_rows(li: NDArray[np.floating[Any]], mask: NDArray[np.bool_]) -> None:
    nv, rows, cols = li.shape
    for job in prange(nv * rows):
        n = job // rows
        r = job - n * rows
        c = 0
        while c < cols:
            if not mask[n, r, c]:
                c += 1
                continue
            start = c
            while c < cols and mask[n, r, c]:
                c += 1
            left = li[n, r, start - 1] if start > 0 else (li[n, r, c] if c < cols else 0.0)
            right = li[n, r, c] if c < cols else left
            span = c - start + 1
            for k in range(start, c):
                t = (k - start + 1) / span
                li[n, r, k] = (1.0 - t) * left + t * right


def fill_traces(li: NDArray[np.float32], mask: NDArray[np.bool_]) -> NDArray[np.float32]:
    """Copy of ``li`` with masked pixels replaced by linear interpolation along detector rows."""
    if li.shape != mask.shape:
        raise ReconError(f"mask {mask.shape} must match projections {li.shape}")
    out = np.array(li, dtype=np.float32, copy=True)
    _fill_rows(out, np.ascontiguousarray(mask))
    return out


def add_metal_back(
    corrected: NDArray[np.float32], first: NDArray[np.float32], metal: NDArray[np.bool_]
) -> NDArray[np.float32]:
    """Corrected volume with the first reconstruction's values restored inside the metal voxels."""
    out = corrected.copy()
    out[metal] = np.maximum(first[metal], corrected[metal])
    return out


def tissue_prior(first: NDArray[np.float32], metal: NDArray[np.bool_]) -> NDArray[np.float32]:
    """Flattened prior of the first volume: air 0, soft tissue one value, bone kept, metal as soft tissue."""
    body = first[(first > 0.005) & ~metal]
    tissue = float(np.median(body)) if body.size else 0.02
    prior = np.where(first < 0.5 * tissue, 0.0, np.where(first < 1.4 * tissue, tissue, first)).astype(np.float32)
    prior[metal] = tissue
    return prior


def fill_traces_normalized(
    li: NDArray[np.float32], mask: NDArray[np.bool_], prior_li: NDArray[np.float32]
) -> NDArray[np.float32]:
    """Interpolate in ``li / prior_li`` (normalized MAR) so structures the prior knows survive in the traces."""
    eps = np.float32(max(float(np.percentile(prior_li, 99)) * 1e-3, 1e-6))
    norm = li / (prior_li + eps)
    return (fill_traces(norm, mask) * (prior_li + eps)).astype(np.float32)
