"""What a calibration found: the result, its per-iteration figures and its summary."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib.quality import CalibrationVerdict
from calib.scale import ScaleBar
from orbitct.geometry import ViewGeometry
from orbitct.statistics import rpe_statistics


@dataclass
class IterationStats:
    """RPE summary of one iteration (index 0 = the initial geometry)."""

    index: int
    rpe_mean_mm: float
    rpe_median_mm: float
    rpe_std_mm: float
    reproj_rms_px: float


@dataclass
class CalibrationResult:
    """What a calibration found and where it was written."""

    method: str
    path: Path
    geometry: ViewGeometry
    nominal: ViewGeometry
    uv: NDArray[np.float64]
    xyz: NDArray[np.float64]
    rpe_mm: NDArray[np.float64]
    n_frames: int
    iterations: list[IterationStats]
    rpe_history: list[NDArray[np.float64]]
    elapsed_s: float
    detect_s: float
    estimate_s: float
    reproj_rms_px: float
    corrections: dict[str, NDArray[Any]]  # rotvec_rad, shift_mm (float) and frame (int) per view
    warnings: list[str] = field(default_factory=list)
    unsolved_views: list[int] = field(default_factory=list)
    true_corrections: dict[str, NDArray[np.float64]] | None = None  # simulated scans: the truth, same frame
    quality: CalibrationVerdict | None = None
    compile_s: float = 0.0  # numba compiling its kernels on first use (after installation); not in elapsed_s
    identify_s: float = 0.0  # telling the BBs apart across the orbit (part of elapsed_s)
    check_s: float = 0.0  # the quality check and the per-view figures (part of elapsed_s)
    write_s: float = 0.0  # writing the geometry into the file (after elapsed_s, which the file records)
    view_status: NDArray[np.int8] | None = None  # per frame: STATUS_CODES, -1 for non-projections
    predicted_px: NDArray[np.float64] | None = None  # per frame: predicted field-of-view error (px)
    scale_bar: ScaleBar | None = None  # the pair of BBs that set the metric scale, when a scale bar was given

    @property
    def n_bbs(self) -> int:
        """Number of BBs found."""
        return int(self.xyz.shape[0])

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary (no per-frame arrays)."""
        last = self.iterations[-1]
        return {
            "method": self.method,
            "path": str(self.path),
            "n_frames": self.n_frames,
            "n_bbs": self.n_bbs,
            "elapsed_s": self.elapsed_s,
            "detect_s": self.detect_s,
            "identify_s": self.identify_s,
            "estimate_s": self.estimate_s,
            "check_s": self.check_s,
            "write_s": self.write_s,
            "compile_s": self.compile_s,
            "rpe_mean_mm": last.rpe_mean_mm,
            "rpe_median_mm": last.rpe_median_mm,
            "rpe_std_mm": last.rpe_std_mm,
            "reproj_rms_px": self.reproj_rms_px,
            "iterations": [asdict(s) for s in self.iterations],
            "warnings": list(self.warnings),
            "unsolved_views": list(self.unsolved_views),
            "quality": self.quality.summary() if self.quality is not None else None,
            "scale": self.scale_line(),
        }

    def timing_line(self) -> str:
        """Where the time went: the phases, summing to ``elapsed_s``, and writing the file apart (compiling the
        kernels on first use is apart too: ``compile_s``)."""
        return (
            f"detection {self.detect_s:.2f} s + identification {self.identify_s:.2f} s + estimation "
            f"{self.estimate_s:.2f} s + checks {self.check_s:.2f} s = {self.elapsed_s:.2f} s; writing "
            f"{self.write_s:.2f} s"
        )

    def scale_line(self) -> str:
        """Where the metric scale comes from, in words."""
        if self.scale_bar is not None:
            return self.scale_bar.describe()
        if self.method != "bundle":
            return "metric scale from the nominal geometry (the paper method fixes no gauge)"
        return (
            "metric scale from the nominal geometry: distances in the calibrated frame can be off by about the "
            "orbit's mean error along the beam over the source distance (1-2 % on the bench profile); a scale bar "
            "fixes it (--scale-bar-mm)"
        )


def iteration_stats(index: int, rpe: NDArray[np.float64], resid_px: NDArray[np.float64]) -> IterationStats:
    st = rpe_statistics(rpe)
    r = resid_px[np.isfinite(resid_px)]
    return IterationStats(
        index, st.mean_mm, st.median_mm, st.std_mm, float(np.sqrt(np.mean(r**2))) if r.size else float("nan")
    )
