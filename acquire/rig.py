"""The rig interface: what the scan engine (:mod:`acquire.engine`) needs from the machine that carries source,
object and detector. The machines themselves, the bench and the C-arm, are in :mod:`acquire.rigs`."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Protocol, runtime_checkable

from acquire.plan import ScanPlan
from devices.frame_protocol import Frame


@runtime_checkable
class Rig(Protocol):
    """What the engine needs from the machine that carries source, object and detector.

    ``axes`` maps every recorded axis (``device.axis``, as in ``/frames/commanded``) to its unit.
    """

    sim: bool

    @property
    def axes(self) -> Mapping[str, str]:
        """Every recorded axis and its unit."""

    async def preflight(self, plan: ScanPlan, mode: str, frame_rate_hz: float) -> None:
        """Check the whole plan against every limit before anything moves (raise :class:`RefusedError`)."""

    async def prepare(self, plan: ScanPlan) -> None:
        """Get ready: servo and references, velocities, X-ray technique, panel armed, program loaded."""

    async def move_to(self, targets: Mapping[str, float], timeout_s: float) -> None:
        """Move every axis to a frame's targets and wait until all are there."""

    def travel_s(self, start: Mapping[str, float], end: Mapping[str, float]) -> float:
        """Wall-clock seconds a move from ``start`` to ``end`` (a frame's targets) takes at the configured speeds,
        acceleration and settling left out (the scan's pace learns them)."""

    async def acquire(
        self, image_key: int, after_exposure: Callable[[], None] | None = None, *, next_exposure_s: float | None = None
    ) -> Frame:
        """One frame: dark, flat or projection; ``after_exposure`` runs once X-rays are off again.
        ``next_exposure_s``: how soon the next exposure is due, where the engine knows it (a sweep)."""

    async def read_positions(self) -> dict[str, float]:
        """Read-back of every recorded axis."""

    async def stop_all(self, *, interrupted: bool = False) -> None:
        """Halt every axis and switch X-rays off, all at once; never raises.

        ``interrupted``: the scan was cancelled in the middle of an exchange, so links may hold a
        late reply and must resynchronise first.
        """

    async def restore(self) -> None:
        """At rest (a complete scan, a pause): X-rays off, speeds back to their configured values."""

    async def close(self) -> None:
        """Stop everything, then disconnect every device."""


@runtime_checkable
class SweepRig(Rig, Protocol):
    """A rig that can also run continuously: one axis (``sweep_axis``) turns at constant speed."""

    sweep_axis: str

    async def start_sweep(self, target: float, velocity: float) -> None:
        """Send ``sweep_axis`` to ``target`` at ``velocity`` (wall-clock units per second); do not wait."""

    async def start_move(self, targets: Mapping[str, float]) -> None:
        """Send the other axes to ``targets`` without waiting (a running move may be retargeted)."""

    async def sweep_position(self) -> float:
        """Read-back of ``sweep_axis``."""

    def last_exposure_s(self) -> tuple[float, float] | None:
        """When the last exposure began and ended (``time.monotonic()``); None while unknown."""


@runtime_checkable
class PreparingRig(Rig, Protocol):
    """A rig whose X-ray source can get ready while the axes move to the next projection.

    ``prep_s``: how long the source takes to get ready (wall clock).
    """

    prep_s: float

    async def prepare_exposure(self) -> None:
        """Bring the source up for the next exposure (it drops again by itself if no exposure follows)."""
