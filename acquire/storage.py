"""Disk space for a scan file: estimated before the scan starts, watched while it runs.

A scan is refused before anything moves when its estimated size plus the reserve
(``storage.reserve_mb``) does not fit; while it runs, the recorder stops it cleanly when
less than half the reserve plus two frames is left, so the file is always closed with
room to spare and never cut by a full disk.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquire.errors import DiskSpaceError
from orbitct.diskspace import MB, format_bytes, free_bytes
from orbitct.geometry import Panel

# per frame besides the pixels: nominal vector and matrix, true vector, time, image key, encoders and
# commanded positions of up to 8 axes, injected errors; plus the HDF5 chunk index (rounded up)
_META_PER_FRAME_BYTES = 12 * 8 * 3 + 8 + 1 + 2 * 8 * 8 + 6 * 8 + 64
_FIXED_BYTES = 2 * MB  # groups, attributes, configuration, truth markers, the file's own structures


def frame_bytes(panel: Panel, frame_dtype: str = "uint16") -> int:
    """Bytes one frame takes in the file, its metadata included."""
    return panel.rows * panel.cols * np.dtype(frame_dtype).itemsize + _META_PER_FRAME_BYTES


def scan_bytes(panel: Panel, n_frames: int, frame_dtype: str = "uint16") -> int:
    """Estimated size of a scan file of ``n_frames`` frames (uncompressed)."""
    return int(n_frames) * frame_bytes(panel, frame_dtype) + _FIXED_BYTES


def check_room(
    out: str | os.PathLike[str], panel: Panel, n_frames: int, reserve_mb: float, frame_dtype: str = "uint16"
) -> int:
    """Refuse a scan whose file would not fit with ``reserve_mb`` left; returns the estimated size in bytes."""
    need = scan_bytes(panel, n_frames, frame_dtype)
    reserve = int(reserve_mb * MB)
    free = free_bytes(Path(out).parent)
    if free < need + reserve:
        raise DiskSpaceError(
            f"not enough disk space for {Path(out).name}, so nothing moved: the scan needs about {format_bytes(need)} "
            f"({n_frames} frames of {panel.rows}x{panel.cols} {frame_dtype}) and {format_bytes(reserve)} must stay free "
            f"(storage.reserve_mb), but only {format_bytes(free)} is free in {Path(out).parent}"
        )
    return need


@dataclass
class SpaceWatch:
    """Checked before every frame is written: stops the scan while there is still room to close its file."""

    folder: Path
    frame_bytes: int
    reserve_bytes: int

    @property
    def floor_bytes(self) -> int:
        """Free space below which the next frame is not written."""
        return 2 * self.frame_bytes + self.reserve_bytes // 2

    def check(self, frames_written: int) -> None:
        """Raise :class:`DiskSpaceError` when the next frame would leave less than :attr:`floor_bytes` free."""
        free = free_bytes(self.folder)
        if free < self.floor_bytes:
            raise DiskSpaceError(
                f"disk nearly full: {format_bytes(free)} free in {self.folder}, less than two frames plus half "
                f"the reserve ({format_bytes(self.floor_bytes)}, storage.reserve_mb); the scan stopped with its "
                f"{frames_written} frames kept"
            )
