"""Live calibration on a bluesky run's document stream: the BBs detected and followed as events arrive, warnings
while the run goes on, and the geometry in the scan file once the run is complete.

Subscribe it after the :class:`~orbitct_bluesky.ScanFileCallback` that writes the same file (the RunEngine calls
callbacks in the order they were subscribed: the file must be closed before the final solve reads it). The run's
``orbitct`` entry must hold the plan's frames (``frames`` of :func:`~orbitct_bluesky.orbitct_metadata`, which
:func:`~orbitct_bluesky.orbit_plan` fills): live calibration needs every frame's kind and nominal view before the
first one arrives.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import event_model
import numpy as np

from calib.follow import LiveWarning
from calib.live import FinalSolve, FinalSolveOutcome, LiveCalibration
from orbitct.geometry import ViewGeometry
from orbitct_bluesky.scanfile_callback import DEFAULT_KEYS, KEY, entry_keys, entry_panel

log = logging.getLogger(__name__)


class LiveCalibrationCallback(FinalSolveOutcome, event_model.DocumentRouter):
    """A bluesky callback calibrating the run written to ``path`` while it runs (BB diameter ``diameter_mm``;
    ``options``: those of ``orbitct calibrate``). ``on_warning`` is called for every warning, in a thread of its
    own. After a complete run, :attr:`result` waits for the final solve, written to ``path`` as ``orbitct
    calibrate`` writes it; a run that did not complete is left for ``orbitct calibrate`` later."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        diameter_mm: float,
        *,
        stream: str = "primary",
        on_warning: Callable[[LiveWarning], None] | None = None,
        **options: Any,
    ) -> None:
        super().__init__()
        self.path = Path(path)
        self.diameter_mm = float(diameter_mm)
        self.stream = stream
        self.on_warning = on_warning
        self.options = options
        self.live: LiveCalibration | None = None
        self._keys: dict[str, str | None] = dict(DEFAULT_KEYS)
        self._descriptors: set[str] = set()
        self._n_frames = 0
        self._final: FinalSolve | None = None

    def start(self, doc: Mapping[str, Any]) -> None:
        md = doc.get(KEY)
        frames = md.get("frames") if isinstance(md, Mapping) else None
        if not isinstance(md, Mapping) or not isinstance(frames, Mapping):
            raise ValueError(
                f"live calibration needs the run's frames in its start document's {KEY!r} entry (image keys and "
                "nominal views: orbitct_metadata(..., frames=...), which orbit_plan fills)"
            )
        panel = entry_panel(md)
        image_key = np.asarray(frames["image_key"], dtype=np.int8)
        nominal = ViewGeometry(np.asarray(frames["nominal_vectors"], dtype=float).reshape(-1, 12), panel)
        self._keys = entry_keys(md)
        self._descriptors, self._n_frames = set(), 0
        self._final = None
        self.live = LiveCalibration(
            self.path, nominal, image_key, self.diameter_mm, on_warning=self.on_warning, **self.options
        )

    def descriptor(self, doc: Mapping[str, Any]) -> None:
        if doc.get("name") == self.stream:
            self._descriptors.add(str(doc["uid"]))

    def event(self, doc: Mapping[str, Any]) -> None:  # type: ignore[override]
        if self.live is None or doc.get("descriptor") not in self._descriptors:
            return
        data = doc["data"]
        key = int(data[str(self._keys["image_key"])])
        self.live.add_frame(self._n_frames, key, np.asarray(data[str(self._keys["image"])]))
        self._n_frames += 1

    def stop(self, doc: Mapping[str, Any]) -> None:
        live, self.live = self.live, None
        if live is None:
            return
        if doc.get("exit_status") != "success":
            live.close()
            return
        self._final = FinalSolve(live)
