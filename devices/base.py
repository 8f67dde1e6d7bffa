"""The device API: the :class:`Driver` base, awaitable :class:`Status`, and capabilities as small protocols.

Actions (moves, exposures, frame reads) return a :class:`Status`: an awaitable
that reports progress to watchers and ends in success or a named
:class:`~devices.errors.DeviceError`.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, Protocol, TypeVar, runtime_checkable

from devices.errors import DeviceTimeoutError, InterlockOpenError
from devices.frame_protocol import Frame

log = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True)
class Progress:
    """One progress report of an action: where it is, where it goes, how far along (0..1)."""

    name: str
    current: Mapping[str, float] = field(default_factory=dict)
    target: Mapping[str, float] = field(default_factory=dict)
    fraction: float = 0.0
    elapsed_s: float = 0.0
    message: str = ""


Watcher = Callable[[Progress], None]


class Status(Generic[T]):
    """Awaitable outcome of an action, with progress reports for watchers."""

    def __init__(self, name: str, coro: Awaitable[T], *, timeout_s: float | None = None) -> None:
        self.name = name
        self._watchers: list[Watcher] = []
        self._t0 = time.monotonic()
        self._last: Progress | None = None
        self._task: asyncio.Task[T] = asyncio.ensure_future(self._run(coro, timeout_s))

    async def _run(self, coro: Awaitable[T], timeout_s: float | None) -> T:
        if timeout_s is None:
            return await coro
        # asyncio.timeout, not wait_for: wait_for can swallow a cancellation on Python 3.11.
        try:
            async with asyncio.timeout(timeout_s):
                return await coro
        except TimeoutError:
            raise DeviceTimeoutError(f"{self.name}: not done within {timeout_s:g} s") from None

    def watch(self, watcher: Watcher) -> None:
        """Call ``watcher`` with every progress report (and the latest one at once)."""
        self._watchers.append(watcher)
        if self._last is not None:
            watcher(self._last)

    def report(self, **kwargs: Any) -> None:
        """Publish progress (used by drivers)."""
        p = Progress(name=self.name, elapsed_s=time.monotonic() - self._t0, **kwargs)
        self._last = p
        for w in list(self._watchers):
            w(p)

    @property
    def done(self) -> bool:
        """Whether the action has ended (either way)."""
        return self._task.done()

    @property
    def success(self) -> bool:
        """Whether the action ended without error."""
        return self._task.done() and not self._task.cancelled() and self._task.exception() is None

    def exception(self) -> BaseException | None:
        """The error the action ended with, if any."""
        if not self._task.done() or self._task.cancelled():
            return None
        return self._task.exception()

    def cancel(self) -> None:
        """Cancel waiting for the action (drivers stop motion in their own cleanup)."""
        self._task.cancel()

    def __await__(self) -> Any:
        return self._task.__await__()

    def __repr__(self) -> str:
        state = "running" if not self.done else ("ok" if self.success else f"failed: {self.exception()!r}")
        return f"Status({self.name!r}, {state})"


@dataclass(frozen=True)
class AxisInfo:
    """One axis: name, unit (``mm`` or ``deg``) and soft limits in that unit."""

    name: str
    unit: str
    low: float
    high: float


@dataclass(frozen=True)
class DeviceInfo:
    """What :meth:`Device.describe` returns."""

    name: str
    model: str
    serial: str
    firmware: str = ""
    axes: tuple[AxisInfo, ...] = ()
    uri: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)


class Driver:
    """What every driver shares: a name, the endpoint URI it connects to, and what to release with it.

    Drivers only ever see real endpoints (``tcp://``, ``serial://``, ``modbus://``, ``folder://``);
    whoever opened something for a driver (``devices.sim`` starts a twin for a ``sim://`` URI)
    attaches its release here, and the driver's ``close()`` runs it.
    """

    def __init__(self, name: str, uri: str) -> None:
        self.name = name
        self.uri = uri
        self._on_close: list[Callable[[], Any]] = []
        # software interlock: returns why nothing may move or expose now (a latched emergency stop), None when it
        # may; asked right before every command that would start motion or switch high voltage on
        self.interlock: Callable[[], str | None] | None = None

    def _check_interlock(self, action: str) -> None:
        """Refuse ``action`` while the software interlock names a reason."""
        reason = self.interlock() if self.interlock is not None else None
        if reason:
            raise InterlockOpenError(f"{self.name}: {action} refused: {reason}; reset the stop first")

    def on_close(self, release: Callable[[], Any]) -> None:
        """Call ``release()`` (a function or coroutine function) once, when this driver closes."""
        self._on_close.append(release)

    async def _release(self) -> None:
        releases, self._on_close = self._on_close, []
        for release in reversed(releases):
            try:
                result = release()
                if asyncio.iscoroutine(result):
                    await result
            except Exception as exc:  # noqa: BLE001 - one failing release must not keep the others
                log.error("%s: releasing %r failed: %s", self.name, release, exc)


@runtime_checkable
class Readable(Protocol):
    """Anything orbitct connects to: it describes itself and reports its state."""

    name: str

    async def connect(self) -> None:
        """Open the transport and check the device answers."""

    async def close(self) -> None:
        """Release the transport (idempotent)."""

    async def describe(self) -> DeviceInfo:
        """Model, serial, axes, units and limits."""

    async def read(self) -> dict[str, Any]:
        """Current state as plain values."""


@runtime_checkable
class Movable(Readable, Protocol):
    """Axes that move to targets."""

    def move(self, targets: Mapping[str, float]) -> Status[None]:
        """Start an absolute move (user units); the status ends when on target."""

    async def stop(self) -> None:
        """Halt every axis now."""

    async def limits(self) -> dict[str, tuple[float, float]]:
        """Soft limits per axis (user units)."""

    async def position(self) -> dict[str, float]:
        """Read-back positions per axis (user units)."""


@runtime_checkable
class Referencing(Movable, Protocol):
    """Servo-controlled axes that must be referenced before they move."""

    async def referenced(self) -> dict[str, bool]:
        """Per axis: referenced."""

    async def servo_on(self) -> dict[str, bool]:
        """Per axis: servo on."""

    async def servo(self, on: bool = True) -> None:
        """Switch every axis's servo on or off."""

    def reference(self) -> Status[None]:
        """Reference every axis (moves them to their switches)."""

    async def set_velocity(self, velocity: float) -> None:
        """Speed of the next moves (mm/s or deg/s)."""


@runtime_checkable
class Triggerable(Readable, Protocol):
    """Something that acts once per frame (exposure, frame grab)."""

    def trigger(self) -> Status[Any]:
        """Start one action; the status ends when it is complete."""


@runtime_checkable
class XraySource(Triggerable, Protocol):
    """An X-ray generator: technique, one exposure per trigger, high voltage off on request.

    ``last_exposure_s``: when the last exposure began and ended (``time.monotonic()``), None while unknown.
    """

    last_exposure_s: tuple[float, float] | None

    async def check_ready(self) -> None:
        """Raise unless the generator could expose now (no fault latched, interlock closed); switches nothing on."""

    async def configure(self, kv: float, ma: float, exposure_ms: float) -> None:
        """Set tube voltage, current and exposure time."""

    def prepare(self) -> Status[None]:
        """High voltage up, ready to expose at once (held for a while, then dropped again by the generator)."""

    def expose(self, *, release: bool = False) -> Status[int]:
        """One exposure; ends with the generator's frame counter (``release``: high voltage off right after it)."""

    async def xray_off(self) -> None:
        """High voltage off now (safe in every state)."""


@runtime_checkable
class FrameSource(Readable, Protocol):
    """A detector: frames on a trigger, darks and flats on request."""

    async def set_trigger(self, mode: str) -> None:
        """``software`` or ``xray`` (a frame for every generator exposure)."""

    async def arm(self) -> None:
        """Get ready to deliver the next frames."""

    async def read_frame(self, timeout_s: float | None = None) -> Frame:
        """The next frame."""

    async def acquire_dark(self, n: int) -> list[Frame]:
        """``n`` frames without X-rays."""

    async def acquire_flat(self, n: int) -> list[Frame]:
        """``n`` open-beam frames."""
