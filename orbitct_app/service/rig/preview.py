"""The newest frame of the running scan, kept by a subscriber in the bench process for the console's live view."""

from __future__ import annotations

import base64
import math
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

IMAGE_KINDS = {0: "projection", 1: "flat", 2: "dark"}  # the scan file's image_key (NXtomo)


class LatestFrame:
    """A scan subscriber that keeps references to the newest frames (no copy, no work per frame).

    ``marks``, when given, returns ``(frame index, [[u, v], ...])`` of the BBs a live calibration found last; the
    snapshot then shows that frame (if still kept) with its BBs, so the marks sit on the picture they belong to."""

    KEEP = 4  # frames kept (references): how far a live calibration may lag and still get its marks drawn

    def __init__(self, marks: Callable[[], tuple[int, list[list[float]]] | None] | None = None) -> None:
        self._records: deque[Any] = deque(maxlen=self.KEEP)
        self._marks = marks
        self._last: tuple[tuple[int, int | None], dict[str, Any]] | None = None

    def on_start(self, start: Any) -> None:
        self._records.clear()
        self._last = None

    def on_frame(self, record: Any) -> None:
        self._records.append(record)

    def on_finish(self, end: Any) -> None:
        pass

    def snapshot(self, max_px: int = 256) -> dict[str, Any] | None:
        """The newest frame, block-averaged to at most ``max_px`` a side and windowed to 8 bits (1st to 99.5th
        percentile); None before the first frame. ``scale`` maps detector pixels to the picture's; ``bbs`` are detector
        pixels (None without a live calibration)."""
        records = list(self._records)
        if not records:
            return None
        record, bbs = records[-1], None
        marked = self._marks() if self._marks is not None else None
        if marked is not None:
            by_index = {r.index: r for r in records}
            if marked[0] in by_index:
                record, bbs = by_index[marked[0]], marked[1]
        key = (record.index, None if bbs is None else len(bbs))
        if self._last is not None and self._last[0] == key:  # many viewers, one frame: computed once
            return self._last[1]
        frame = np.asarray(record.frame, dtype=np.float32)
        step = max(1, math.ceil(max(frame.shape) / max_px))
        rows, cols = (frame.shape[0] // step) * step, (frame.shape[1] // step) * step
        small = frame[:rows, :cols].reshape(rows // step, step, cols // step, step).mean(axis=(1, 3))
        lo, hi = np.percentile(small, [1.0, 99.5])
        grey = np.clip((small - lo) / max(float(hi - lo), 1e-6) * 255.0, 0, 255).astype(np.uint8)
        snapshot = {
            "index": int(record.index),
            "kind": IMAGE_KINDS.get(int(record.image_key), "frame"),
            "width": int(grey.shape[1]),
            "height": int(grey.shape[0]),
            "scale": 1.0 / step,
            "pixels": base64.b64encode(grey.tobytes()).decode("ascii"),
            "bbs": bbs,
        }
        self._last = (key, snapshot)
        return snapshot
