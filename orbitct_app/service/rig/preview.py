"""The newest frame of the running scan, kept by a subscriber in the bench process for the console's live view."""

from __future__ import annotations

import base64
import math
import threading
from typing import Any

import numpy as np

IMAGE_KINDS = {0: "projection", 1: "flat", 2: "dark"}  # the scan file's image_key (NXtomo)


class LatestFrame:
    """A scan subscriber that keeps a reference to the newest frame (no copy, no work per frame)."""

    def __init__(self) -> None:
        self._record: Any = None
        self._lock = threading.Lock()

    def on_start(self, start: Any) -> None:
        with self._lock:
            self._record = None

    def on_frame(self, record: Any) -> None:
        self._record = record

    def on_finish(self, end: Any) -> None:
        pass

    def snapshot(self, max_px: int = 256) -> dict[str, Any] | None:
        """The newest frame, block-averaged to at most ``max_px`` a side and windowed to 8 bits (1st to 99.5th
        percentile); None before the first frame. ``scale`` maps detector pixels to the picture's."""
        record = self._record
        if record is None:
            return None
        frame = np.asarray(record.frame, dtype=np.float32)
        step = max(1, math.ceil(max(frame.shape) / max_px))
        rows, cols = (frame.shape[0] // step) * step, (frame.shape[1] // step) * step
        small = frame[:rows, :cols].reshape(rows // step, step, cols // step, step).mean(axis=(1, 3))
        lo, hi = np.percentile(small, [1.0, 99.5])
        grey = np.clip((small - lo) / max(float(hi - lo), 1e-6) * 255.0, 0, 255).astype(np.uint8)
        return {"index": int(record.index), "kind": IMAGE_KINDS.get(int(record.image_key), "frame"),
                "width": int(grey.shape[1]), "height": int(grey.shape[0]), "scale": 1.0 / step,
                "pixels": base64.b64encode(grey.tobytes()).decode("ascii")}
