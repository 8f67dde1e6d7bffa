"""Subscriber that writes the scan file (``scan-file.md``) as frames arrive."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from acquire.records import FrameRecord, ScanEnd, ScanStart
from orbitct.scanfile import ImageKey, ScanWriter


class ScanRecorder:
    """Streams frames, image keys, times, axes and nominal geometry into ``path``; finishes with the status."""

    def __init__(self, path: str | os.PathLike[str], *, overwrite: bool = False, frame_dtype: str = "uint16",
                 marker_diameter_mm: float | None = None) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.frame_dtype = frame_dtype
        self.marker_diameter_mm = marker_diameter_mm
        self.writer: ScanWriter | None = None
        self._truth: np.ndarray | None = None
        self.n_written = 0

    def on_start(self, start: ScanStart) -> None:
        """Create the file with detector, axes, orbit and configuration provenance."""
        plan = start.plan
        self.writer = ScanWriter(
            self.path, plan.panel, frame_dtype=self.frame_dtype, axes=dict(start.axes),
            orbit_name=plan.orbit_name, orbit_params=dict(plan.orbit_params), config=dict(plan.config),
            marker_diameter_mm=self.marker_diameter_mm, overwrite=self.overwrite,
        )
        self.writer.set_attrs(
            "acquisition", mode=start.mode, error_profile=plan.error_profile, planned_frames=plan.n_frames,
            planned_projections=plan.n_projections, started_utc=start.started_utc, simulated=bool(start.sim),
            **dict(start.extra),
        )
        # per-frame injected errors (pitch, roll, yaw rad; x, y, z mm), NaN rows for darks and flats
        errors = np.where((plan.image_key == ImageKey.PROJECTION)[:, None], plan.errors, np.nan)
        self.writer.write_dataset("acquisition/injected_errors", errors, columns="pitch_rad roll_rad yaw_rad x_mm y_mm z_mm")
        self._truth = np.full((plan.n_frames, 12), np.nan) if start.sim else None

    def on_frame(self, record: FrameRecord) -> None:
        """Append one frame and flush it to disk."""
        assert self.writer is not None, "on_start was not called"
        vec = record.nominal_vector if record.image_key == ImageKey.PROJECTION else None
        self.writer.append(
            record.frame, record.image_key, record.time_s, nominal_vector=vec,
            encoders=dict(record.encoders), commanded=dict(record.commanded),
        )
        if self._truth is not None and record.true_vector is not None and record.image_key == ImageKey.PROJECTION:
            self._truth[record.index] = record.true_vector
        self.n_written = self.writer.n_frames

    def on_finish(self, end: ScanEnd) -> None:
        """Store the simulation truth (if any) and the final status, then close the file."""
        if self.writer is None:
            return
        try:
            if self._truth is not None:
                truth: dict[str, Any] = dict(end.truth)
                self.writer.write_truth(self._truth[: self.writer.n_frames], truth.get("markers_xyz"), truth.get("phantom"))
        finally:
            self.writer.finish(end.status, end.reason)
