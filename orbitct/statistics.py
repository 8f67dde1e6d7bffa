"""Summary statistics shared by calibration, scan files, reports and the service (one definition each)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


@dataclass(frozen=True)
class RpeStatistics:
    """Mean, median and standard deviation (mm) of per-frame RPE over the frames that have one."""

    mean_mm: float
    median_mm: float
    std_mm: float
    n_frames: int

    def as_attrs(self) -> dict[str, float]:
        """The ``rpe_mean_mm``, ``rpe_median_mm``, ``rpe_std_mm`` attributes of ``/geometry/calibrated``."""
        return {"rpe_mean_mm": self.mean_mm, "rpe_median_mm": self.median_mm, "rpe_std_mm": self.std_mm}


def rpe_statistics(rpe_mm: ArrayLike) -> RpeStatistics:
    """Statistics of a per-frame RPE array (NaN frames are left out; all NaN when no frame has one)."""
    r = np.asarray(rpe_mm, dtype=float).ravel()
    ok = r[np.isfinite(r)]
    if ok.size == 0:
        return RpeStatistics(float("nan"), float("nan"), float("nan"), 0)
    return RpeStatistics(float(ok.mean()), float(np.median(ok)), float(ok.std()), int(ok.size))
