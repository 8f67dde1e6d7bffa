"""What the engine tells its subscribers: scan start, one record per frame, scan end."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from acquire.plan import ScanPlan


@dataclass(frozen=True)
class ScanStart:
    """A scan is about to take its first frame."""

    plan: ScanPlan
    axes: Mapping[str, str]
    mode: str
    started_utc: str
    sim: bool = False
    extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class FrameRecord:
    """One acquired frame with everything known about it when it was taken.

    ``true_vector`` is the view a simulated panel rendered the frame at (from the frame's
    metadata); real hardware leaves it None.
    """

    index: int
    image_key: int
    view: int
    time_s: float
    frame: NDArray[Any]
    commanded: Mapping[str, float]
    encoders: Mapping[str, float]
    nominal_vector: NDArray[np.float64]
    true_vector: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class ScanEnd:
    """The scan is over: ``complete`` or ``aborted`` (with the reason), and how many frames were written."""

    status: str
    reason: str
    n_frames: int
    elapsed_s: float


class Subscriber(Protocol):
    """Receives the engine's events in order, in the engine's thread. A subscriber that starts work of its own may
    also have an ``async ready()``: the engine awaits it after ``on_start`` and before the first frame."""

    def on_start(self, start: ScanStart) -> None:
        """Before the first frame."""

    def on_frame(self, record: FrameRecord) -> None:
        """After each frame; when this returns, the frame counts as written."""

    def on_finish(self, end: ScanEnd) -> None:
        """Once, on every exit path."""
