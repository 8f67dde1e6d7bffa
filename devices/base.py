"""The device API every driver implements: describe, read, and capabilities as small protocols.

Actions (moves, exposures, frame reads) return a :class:`Status`: an awaitable
that reports progress to watchers and ends in success or a named
:class:`~devices.errors.DeviceError`.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, Protocol, TypeVar, runtime_checkable

from devices.errors import DeviceError, DeviceTimeoutError

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


@runtime_checkable
class Device(Protocol):
    """Anything orbitct can connect to."""

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
class Movable(Protocol):
    """Axes that move to targets."""

    def move(self, targets: Mapping[str, float]) -> Status[None]:
        """Start an absolute move (user units); the status ends when on target."""

    async def stop(self) -> None:
        """Halt every axis now."""

    async def limits(self) -> dict[str, tuple[float, float]]:
        """Soft limits per axis (user units)."""

    async def on_target(self) -> bool:
        """Whether every axis has reached its target."""

    async def position(self) -> dict[str, float]:
        """Read-back positions per axis (user units)."""


@runtime_checkable
class Triggerable(Protocol):
    """Something that acts once per frame (exposure, frame grab)."""

    def trigger(self) -> Status[Any]:
        """Start one action; the status ends when it is complete."""


def raise_if_failed(status: Status[Any]) -> None:
    """Raise the status's error if it failed (for synchronous checks)."""
    exc = status.exception()
    if exc is not None:
        raise exc if isinstance(exc, DeviceError) else DeviceError(f"{status.name}: {exc}")
