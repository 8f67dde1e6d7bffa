"""Projections of a scan file read on demand: line integrals and PWLS weights of chosen frames, sliceable along
views like an array (never the whole stack in memory)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from orbitct.scanfile import ScanFile
from recon.pwls import statistical_weights


class FileLineIntegrals:
    """Line integrals of chosen frames read from the scan file on demand (sliceable along views)."""

    def __init__(self, scan: ScanFile, frames: NDArray[np.intp]) -> None:
        self._scan = scan
        self._frames = frames
        self.shape = (frames.size,) + scan.panel.shape

    def __getitem__(self, index: slice | NDArray[np.intp]) -> NDArray[np.float32]:
        return np.stack([self._frame(int(i)) for i in self._frames[index]])

    def _frame(self, i: int) -> NDArray[np.float32]:
        return self._scan.line_integrals(i)


class FileWeights(FileLineIntegrals):
    """PWLS statistical weights of chosen frames computed from the scan file's raw counts on demand."""

    def _frame(self, i: int) -> NDArray[np.float32]:
        dark, flat = self._scan.dark_flat()
        return statistical_weights(self._scan.frames[i], dark, flat)


__all__ = ["FileLineIntegrals", "FileWeights"]
