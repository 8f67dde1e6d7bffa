"""What every twin shares: one thread host, one fault injector, one garbler.

A twin is an object with ``scheme`` (``tcp`` or ``modbus``), ``faults``, and the
coroutines ``start(host, port) -> port`` and ``stop()``. :class:`TwinThread` runs it
in an event loop of its own on a daemon thread, so a twin can live inside the
driver's process (``sim://`` URIs, tests) or standalone (``orbitct twin ...``).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

START_TIMEOUT_S = 300.0  # a twin may compile its renderer's kernels before it listens (first run, no numba cache)


@dataclass
class TwinFaults:
    """Faults a twin injects on request; the counters apply to the next N requests (or frames).

    ``match`` restricts the counted faults to requests containing that text (a GCS command
    name such as ``MOV``, a Modbus request such as ``fc5:1=[1]``, a frame-protocol verb such
    as ``TRIG``). GCS controllers also take per-command error codes (:meth:`add_error`).
    """

    latency_s: float = 0.0  # added before every reply
    drop_next: int = 0  # close the connection instead of answering
    drop_executes: bool = True  # a dropped request still runs before the connection closes
    garble_next: int = 0  # answer with corrupted bytes
    error_next: int = 0  # answer with a device error
    missing_frame_next: int = 0  # complete the action but lose the frame (or trigger)
    misanswer_next: int = 0  # Modbus: answer a register read as the other kind (holding <-> input), as a faulty gateway
    match: str = ""
    errors: dict[str, list[int]] = field(default_factory=dict)  # GCS command -> error codes to report next
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def take(self, name: str, request: str = "") -> bool:
        """Consume one pending fault called ``name`` (``drop``, ``garble``, ``error``, ``missing_frame``, ``misanswer``)
        for ``request``."""
        attr = f"{name}_next"
        with self.lock:
            if self.match and self.match not in request:
                return False
            if getattr(self, attr) > 0:
                setattr(self, attr, getattr(self, attr) - 1)
                return True
            return False

    def add_error(self, code: int, command: str = "MOV", times: int = 1) -> None:
        """Make the next ``times`` ``command`` commands fail with controller error ``code`` (not executed)."""
        with self.lock:
            self.errors.setdefault(command.upper(), []).extend([int(code)] * times)

    def take_error(self, command: str) -> int:
        """The injected error code for this command, if any (consumed)."""
        with self.lock:
            codes = self.errors.get(command.upper())
            return codes.pop(0) if codes else 0

    def clear(self) -> None:
        """Remove every pending fault."""
        with self.lock:
            self.latency_s, self.match = 0.0, ""
            self.drop_next = self.garble_next = self.error_next = self.missing_frame_next = self.misanswer_next = 0
            self.drop_executes = True
            self.errors.clear()


def garble(data: bytes, start: int = 0, stop: int | None = None) -> bytes:
    """Corrupt ``data[start:stop]`` (bit flips) so that a careful client notices; framing outside it stays.

    No line feed is ever produced inside the span, so line-framed protocols still see one reply.
    """
    stop = len(data) if stop is None else stop
    if stop <= start:
        return b"\xff" + data
    bad = bytes(b ^ 0x5A for b in data[start:stop]).replace(b"\n", b"?")
    return data[:start] + bad + data[stop:]


class Twin(Protocol):
    """What :class:`TwinThread` runs."""

    scheme: ClassVar[str]
    faults: TwinFaults

    async def start(self, host: str, port: int) -> int: ...

    async def stop(self) -> None: ...


class TwinThread:
    """Run a twin in its own event loop on a daemon thread; ``uri`` is where it listens."""

    def __init__(self, twin: Twin, host: str = "127.0.0.1", port: int = 0) -> None:
        self.twin = twin
        self.host = host
        self.loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.port = 0
        self._thread = threading.Thread(
            target=self._main, args=(port,), name=f"twin-{type(twin).__name__}", daemon=True
        )
        self._thread.start()
        self._ready.wait(START_TIMEOUT_S)
        if self._error is not None:
            raise self._error
        if not self.port:
            raise RuntimeError(f"{type(twin).__name__} twin did not start within {START_TIMEOUT_S:g} s")

    @property
    def uri(self) -> str:
        """The twin's endpoint, e.g. ``tcp://127.0.0.1:41234`` or ``modbus://127.0.0.1:41235``."""
        return f"{self.twin.scheme}://{self.host}:{self.port}"

    @property
    def faults(self) -> TwinFaults:
        """The twin's fault injector."""
        return self.twin.faults

    @property
    def alive(self) -> bool:
        """Whether the twin still serves."""
        return self._thread.is_alive()

    def _main(self, port: int) -> None:
        asyncio.set_event_loop(self.loop)
        try:
            self.port = self.loop.run_until_complete(self.twin.start(self.host, port))
        except BaseException as exc:  # noqa: BLE001 - reported to the starting thread
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        self.loop.run_forever()

    def call(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run ``fn(*args)`` in the twin's loop (thread-safe, without waiting)."""
        self.loop.call_soon_threadsafe(fn, *args)

    def run(self, coro: Awaitable[Any], timeout_s: float = 10.0) -> Any:
        """Run a coroutine in the twin's loop and wait for its result."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)  # type: ignore[arg-type]

    def run_sync(self, fn: Callable[[], Any], timeout_s: float = 10.0) -> Any:
        """Run ``fn()`` in the twin's loop and wait for its result."""

        async def wrapper() -> Any:
            return fn()

        return self.run(wrapper(), timeout_s)

    def stop(self) -> None:
        """Stop the twin, cancel what still runs in its loop, end the thread (idempotent)."""
        if not self._thread.is_alive():
            return
        try:
            self.run(self.twin.stop(), 5.0)
            self.run(_cancel_others(), 5.0)
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(5.0)
            if not self._thread.is_alive():
                self.loop.close()


async def _cancel_others() -> None:
    """Cancel every other task of the running loop and wait for them to finish."""
    tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
