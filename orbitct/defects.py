"""Defective detector pixels, found from a scan's darks and flats and filled from their row neighbours.

A flat panel has pixels, and sometimes whole columns, that do not respond to X-rays: they read their dark offset in
the flats too. Normalised, such a pixel reads as if nothing got through, an infinite line integral that detection
takes for a BB's edge and reconstruction smears into a streak. A pixel whose open-field response (flat minus dark)
is below :data:`DEAD_RESPONSE` of the panel's median response is taken as defective; its value in each frame is
interpolated from the nearest good pixels left and right of it in its row (a dead column is filled from the columns
beside it; at the panel's edge the nearest good pixel is copied).
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
        """The pixels that barely respond to X-rays (flat minus dark), and their fill from row neighbours."""
        response = np.asarray(flat, dtype=np.float64) - np.asarray(dark, dtype=np.float64)
        typical = float(np.median(response))
        bad = response < DEAD_RESPONSE * typical if typical > 0 else np.zeros(response.shape, dtype=bool)
        rows, cols = bad.shape
        bad_rows, bad_cols = np.nonzero(bad)
        if bad_rows.size == 0 or bad.all(axis=1).any():  # nothing to fill, or a row with nothing to fill from
            empty = np.zeros(0, dtype=np.intp)
            return cls((rows, cols), empty, empty, empty, np.zeros(0))
        col = np.arange(cols)
        good_left = np.where(~bad, col[None, :], -1)
        np.maximum.accumulate(good_left, axis=1, out=good_left)
        good_right = np.where(~bad, col[None, :], cols)
        good_right = np.minimum.accumulate(good_right[:, ::-1], axis=1)[:, ::-1]
        lo, hi = good_left[bad_rows, bad_cols], good_right[bad_rows, bad_cols]
        lo = np.where(lo < 0, hi, lo)  # at an edge: the one neighbour there is
        hi = np.where(hi >= cols, lo, hi)
        span = np.maximum(hi - lo, 1)
        weight = np.where(hi == lo, 0.0, (bad_cols - lo) / span)
        base = bad_rows * cols
        return cls((rows, cols), base + bad_cols, base + lo, base + hi, weight)

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


__all__ = ["DEAD_RESPONSE", "DefectMap"]
