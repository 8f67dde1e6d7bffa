"""Live calibration as a subscriber of the acquisition, beside the recorder (for the CLI and the REST service).

The engine hands every frame to :class:`LiveCalibrationSubscriber` after the recorder; the subscriber only
queues it for :class:`calib.live.LiveCalibration` (its own thread). When the recorder has closed a complete
file, the subscriber finishes the calibration in a thread of its own, which writes ``/geometry/calibrated`` and says
in ``/acquisition@live_calibration`` whether it did; a worker that died leaves the scan complete and the reason there. A warning of a kind named
in ``abort_on`` aborts the scan at the next frame through the engine's own path: axes halted, X-rays off, the
file aborted with the warning as its reason.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from acquire.errors import AcquireError
from acquire.records import FrameRecord, ScanEnd, ScanStart
from calib.errors import CalibrationError
from calib.live import FinalSolve, FinalSolveOutcome, LiveCalibration, LiveSettings, LiveWarning
from orbitct.livewarnings import WARNING_KINDS
from orbitct.progress import ProgressCallback

log = logging.getLogger(__name__)


class LiveWarningAbort(AcquireError):
    """The scan stopped on a live calibration warning the operator chose to stop on."""


class LiveCalibrationSubscriber(FinalSolveOutcome):
    """Calibrates the scan being recorded to ``path`` while it runs (see the module's description)."""

    def __init__(
        self,
        path: str | Path,
        diameter_mm: float,
        *,
        abort_on: Iterable[str] = (),
        lost_frames: int = 10,
        progress: ProgressCallback | None = None,
        on_warning: Callable[[LiveWarning], None] | None = None,
        **options: Any,
    ) -> None:
        unknown = sorted(set(abort_on) - set(WARNING_KINDS))
        if unknown:
            raise CalibrationError(f"abort_on: unknown warning kind(s) {unknown}; allowed are {list(WARNING_KINDS)}")
        if not diameter_mm or not diameter_mm > 0:
            raise CalibrationError(f"live calibration needs the BB diameter in mm (> 0), got {diameter_mm!r}")
        self.path = Path(path)
        self.diameter_mm = float(diameter_mm)
        self.abort_on = frozenset(abort_on)
        self.settings = LiveSettings(lost_frames=int(lost_frames))
        self.progress = progress
        self.on_warning = on_warning
        self.options = options
        self.live: LiveCalibration | None = None
        self._stop_reason: str | None = None
        self._lock = threading.Lock()
        self._final: FinalSolve | None = None

    def _warned(self, w: LiveWarning) -> None:  # in the calibration's thread
        if self.on_warning is not None:
            self.on_warning(w)
        if w.kind in self.abort_on:
            with self._lock:
                if self._stop_reason is None:
                    self._stop_reason = f"stopped on a live calibration warning ({w.kind}): {w.message}"

    def on_start(self, start: ScanStart) -> None:
        """Before the first frame: the plan gives every frame's nominal geometry and kind; starts the worker."""
        self.live = LiveCalibration(
            self.path,
            start.plan.nominal,
            start.plan.image_key,
            self.diameter_mm,
            settings=self.settings,
            progress=self.progress,
            on_warning=self._warned,
            **self.options,
        )

    async def ready(self) -> None:
        """Awaited by the engine before the first frame: returns once the worker follows frames (it starts in a
        process of its own at low priority: seconds on a busy machine), so that its warnings, and a stop on them,
        come while the scan runs. The scan's event loop stays free meanwhile."""
        if self.live is None:
            return
        try:
            await asyncio.to_thread(self.live.wait_ready)
        except CalibrationError:
            self.live.close()
            raise

    def on_frame(self, record: FrameRecord) -> None:
        """Queue the frame (returns at once); stop the scan if a chosen warning came up."""
        with self._lock:
            reason = self._stop_reason
        if reason is not None:
            raise LiveWarningAbort(reason)
        assert self.live is not None
        self.live.add_frame(record.index, record.image_key, record.frame)

    def on_finish(self, end: ScanEnd) -> None:
        """After the recorder closed the file: a complete scan's final solve starts in a thread of its own (the
        scan's loop, and the signals it handles, stay free; :meth:`wait` for it); any other scan keeps its frames
        for ``orbitct calibrate`` later."""
        if self.live is None:
            return
        if end.status != "complete":
            self.live.close()
            return
        self._final = FinalSolve(self.live)

    @property
    def warnings(self) -> list[LiveWarning]:
        """Every warning raised so far."""
        return [] if self.live is None else list(self.live.warnings)


__all__ = ["LiveCalibrationSubscriber", "LiveWarningAbort"]
