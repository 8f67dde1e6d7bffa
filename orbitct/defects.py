"""Defective detector pixels, found from a scan's darks and flats and filled from their row neighbours.

A flat panel has pixels, and sometimes whole columns, that do not respond to X-rays: they read their dark offset in
the flats too. Normalised, such a pixel reads as if nothing got through, an infinite line integral that detection
takes for a BB's edge and reconstruction smears into a streak. A pixel whose open-field response (flat minus dark)
is below :data:`DEAD_RESPONSE` of the panel's median response is taken as defective; its value in each frame is
interpolated from the nearest good pixels left and right of it in its row (a dead column is filled from the columns
beside it; at the panel's edge the nearest good pixel is copied; a whole dead row from the rows above and below).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

ImageT = TypeVar("ImageT", bound=np.ndarray[Any, Any])

#: a pixel responding less than this share of the panel's median open-field response is defective
DEAD_RESPONSE = 0.2


@dataclass(frozen=True)
class DefectMap:
    """Where a panel's defective pixels are, and from which neighbours each is filled (flat indices)."""

    shape: tuple[int, int]
    pixels: NDArray[np.intp]  # flat indices of the defective pixels
    left: NDArray[np.intp]  # flat index of the nearest good pixel to the left (or the right one at the edge)
    right: NDArray[np.intp]
    weight: NDArray[np.float64]  # of the right neighbour

    @classmethod
    def from_dark_flat(cls, dark: NDArray[np.floating], flat: NDArray[np.floating]) -> DefectMap:
        """The pixels that barely respond to X-rays (flat minus dark), and their fill from row neighbours (a whole
        dead row from the rows above and below it)."""
        response = np.asarray(flat, dtype=np.float64) - np.asarray(dark, dtype=np.float64)
        typical = float(np.median(response))
        bad: NDArray[np.bool_] = (
            response < DEAD_RESPONSE * typical if typical > 0 else np.zeros(response.shape, dtype=bool)
        )
        rows, cols = bad.shape
        dead_row: NDArray[np.bool_] = np.asarray(bad.all(axis=1))
        r, c, lo, hi, weight = _fill_along_rows(bad, bad & ~dead_row[:, None])
        rv, cv, lov, hiv, weightv = _fill_along_rows(bad.T, (bad & dead_row[:, None]).T)  # rows of bad.T: columns
        return cls(
            (rows, cols),
            np.concatenate([r * cols + c, cv * cols + rv]),
            np.concatenate([r * cols + lo, lov * cols + rv]),
            np.concatenate([r * cols + hi, hiv * cols + rv]),
            np.concatenate([weight, weightv]),
        )

    @property
    def count(self) -> int:
        """How many pixels are defective."""
        return int(self.pixels.size)

    def filled(self, image: ImageT) -> ImageT:
        """A copy of ``image`` (this panel's shape) with its defective pixels interpolated from their row neighbours
        (rounded for an integer image); ``image`` itself when there are none."""
        if not self.count:
            return image
        out = image.copy()
        flat = out.reshape(-1)
        values = (1.0 - self.weight) * flat[self.left].astype(np.float64) + self.weight * flat[self.right]
        if np.issubdtype(out.dtype, np.integer):
            info = np.iinfo(out.dtype)
            values = np.clip(np.rint(values), info.min, info.max)
        flat[self.pixels] = values
        return out


def _fill_along_rows(
    bad: NDArray[np.bool_], fill: NDArray[np.bool_]
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """For each pixel of ``fill`` (row, col): the columns of the nearest good pixels left and right of it in its row
    (the one there is at an edge) and the right one's weight; pixels with no good pixel in their row are left out."""
    cols = bad.shape[1]
    r, c = np.nonzero(fill)
    col = np.arange(cols)
    good_left = np.maximum.accumulate(np.where(~bad, col[None, :], -1), axis=1)
    good_right = np.minimum.accumulate(np.where(~bad, col[None, :], cols)[:, ::-1], axis=1)[:, ::-1]
    lo, hi = good_left[r, c], good_right[r, c]
    keep = (lo >= 0) | (hi < cols)
    r, c, lo, hi = r[keep], c[keep], lo[keep], hi[keep]
    lo = np.where(lo < 0, hi, lo)  # at an edge: the one neighbour there is
    hi = np.where(hi >= cols, lo, hi)
    weight = np.where(hi == lo, 0.0, (c - lo) / np.maximum(hi - lo, 1))
    return r, c, lo, hi, weight


__all__ = ["DEAD_RESPONSE", "DefectMap"]
