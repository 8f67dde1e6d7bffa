"""Subscriber that writes the scan file (``docs/scan-file.md``) as frames arrive."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from acquire.records import FrameRecord, ScanEnd, ScanStart
from acquire.storage import SpaceWatch, frame_bytes
from orbitct.diskspace import MB
from orbitct.scanfile import ImageKey, ScanWriter


@dataclass(frozen=True)
class SimulationTruth:
    """What a simulated scan was made from, known before its first frame: marker centres and phantom."""

    markers_xyz: NDArray[np.float64]
    phantom: Mapping[str, Any]


class ScanRecorder:
    """Streams frames, image keys, times, axes and nominal geometry into ``path``; finishes with the status.

    A simulated scan (``truth`` given) also gets its truth: marker centres and phantom at the start,
    the true view of every projection with its frame, so a scan cut anywhere is complete up to there.
    With ``reserve_mb`` it watches the free space and stops the scan (raising) while the file can still be closed.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        overwrite: bool = False,
        frame_dtype: str = "uint16",
        marker_diameter_mm: float | None = None,
        truth: SimulationTruth | None = None,
        reserve_mb: float | None = None,
    ) -> None:
        self.path = Path(path)
        self.reserve_mb = reserve_mb
        self.watch: SpaceWatch | None = None
        self.overwrite = overwrite
        self.frame_dtype = frame_dtype
        self.marker_diameter_mm = marker_diameter_mm
        self.truth = truth
        self.writer: ScanWriter | None = None

    def on_start(self, start: ScanStart) -> None:
        """Create the file with panel, axes, orbit, configuration provenance and (simulated) truth."""
        plan = start.plan
        if self.reserve_mb is not None:
            self.watch = SpaceWatch(
                self.path.resolve().parent, frame_bytes(plan.panel, self.frame_dtype), int(self.reserve_mb * MB)
            )
            self.watch.check(0)
        self.writer = ScanWriter(
            self.path,
            plan.panel,
            frame_dtype=self.frame_dtype,
            axes=dict(start.axes),
            orbit_name=plan.orbit_name,
            orbit_params=dict(plan.orbit_params),
            config=dict(plan.config),
            marker_diameter_mm=self.marker_diameter_mm,
            true_geometry=self.truth is not None,
            overwrite=self.overwrite,
        )
        self.writer.set_attrs(
            "acquisition",
            mode=start.mode,
            error_profile=plan.error_profile,
            planned_frames=plan.n_frames,
            planned_projections=plan.n_projections,
            started_utc=start.started_utc,
            simulated=bool(start.sim),
            **dict(start.extra),
        )
        # per-frame injected errors (pitch, roll, yaw rad; x, y, z mm), NaN rows for darks and flats
        errors = np.where((plan.image_key == ImageKey.PROJECTION)[:, None], plan.errors, np.nan)
        self.writer.write_dataset(
            "acquisition/injected_errors", errors, columns="pitch_rad roll_rad yaw_rad x_mm y_mm z_mm"
        )
        if self.truth is not None:
            self.writer.write_truth(markers_xyz=self.truth.markers_xyz, phantom=self.truth.phantom)

    def on_frame(self, record: FrameRecord) -> None:
        """Append one frame (and its true view, when simulated) and flush it to disk."""
        assert self.writer is not None, "on_start was not called"
        if self.watch is not None:
            self.watch.check(self.writer.n_frames)
        projection = record.image_key == ImageKey.PROJECTION
        self.writer.append(
            record.frame,
            record.image_key,
            record.time_s,
            nominal_vector=record.nominal_vector if projection else None,
            encoders=dict(record.encoders),
            commanded=dict(record.commanded),
            true_vector=record.true_vector if projection else None,
        )

    def on_finish(self, end: ScanEnd) -> None:
        """Store the final status and close the file."""
        if self.writer is not None:
            self.writer.finish(end.status, end.reason)
