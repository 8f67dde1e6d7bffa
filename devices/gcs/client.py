"""Asynchronous GCS 2.0 client: one request/reply at a time, ``ERR?`` after set commands.

Queries are safe to repeat, so a query that times out, finds the connection
dropped or gets a garbled reply is retried once over a fresh connection. Set
commands (moves above all) are never repeated: a lost connection raises and
says the command may or may not have run.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TypeVar, overload

from devices.errors import DeviceError, DeviceTimeoutError, NotConnectedError, ProtocolError
from devices.gcs.errors import controller_error
from devices.gcs.framing import encode_command, split_reply
from devices.gcs.transport import Transport, transport_for
from devices.uri import Endpoint

T = TypeVar("T")
_RETRYABLE = (DeviceTimeoutError, NotConnectedError, ProtocolError)


class GcsClient:
    """A GCS 2.0 conversation with one controller over TCP or serial."""

    def __init__(self, endpoint: Endpoint, *, timeout_s: float = 2.0, query_retries: int = 1) -> None:
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self.query_retries = query_retries
        self.stats = {"queries": 0, "commands": 0, "reconnects": 0, "retries": 0}
        self._transport: Transport | None = None
        self._lock = asyncio.Lock()
        self._stale = False  # a reply may still be in flight: reconnect before the next exchange
        self._reconnected: asyncio.Event | None = None  # unset while a reconnect is under way

    @property
    def connected(self) -> bool:
        """Whether a transport is open."""
        return self._transport is not None

    async def connect(self) -> None:
        """Open the transport."""
        transport = transport_for(self.endpoint)
        await transport.open()
        self._transport, self._stale = transport, False

    async def close(self) -> None:
        """Close the transport (idempotent)."""
        transport, self._transport = self._transport, None
        if transport is not None:
            await transport.close()

    async def _reconnect(self) -> None:
        done = self._reconnected = asyncio.Event()
        try:
            await self.close()
            self.stats["reconnects"] += 1
            if self.endpoint.scheme == "serial":  # a serial line keeps late replies: let them arrive, then flush them
                await asyncio.sleep(min(self.timeout_s, 0.5))
            await self.connect()
        finally:
            done.set()

    async def _exchange(self, command: str) -> list[str]:
        if self._transport is None:
            raise NotConnectedError(f"{self.endpoint}: not connected (call connect() first)")
        if self._stale:
            await self._reconnect()
        assert self._transport is not None
        try:
            await self._transport.write(encode_command(command))
            raw = await self._transport.read_reply(self.timeout_s)
        except BaseException:  # timeout, lost connection, or cancelled mid-exchange: a reply may be pending
            self._stale = True
            raise
        try:
            return split_reply(raw)
        except ProtocolError:
            self._stale = True
            raise

    @overload
    async def query(self, command: str) -> list[str]: ...

    @overload
    async def query(self, command: str, parse: Callable[[list[str]], T]) -> T: ...

    async def query(self, command: str, parse: Callable[[list[str]], T] | None = None) -> T | list[str]:
        """Send a query and return its reply lines (or ``parse(lines)``); retried on transport faults."""
        attempts = 1 + max(0, self.query_retries)
        async with self._lock:
            for attempt in range(attempts):
                self.stats["queries"] += 1
                try:
                    lines = await self._exchange(command)
                    return parse(lines) if parse is not None else lines
                except _RETRYABLE as exc:
                    if isinstance(exc, ProtocolError):
                        self._stale = True
                    if attempt + 1 >= attempts:
                        raise type(exc)(f"{exc} (query {command!r}, {attempts} attempts)") from None
                    self.stats["retries"] += 1
        raise AssertionError("unreachable")

    async def command(self, command: str, *, check: bool = True) -> None:
        """Send a set command and, if ``check``, raise the named error for a non-zero ``ERR?``."""
        async with self._lock:
            await self._send_set(command, check)

    async def _send_set(self, command: str, check: bool) -> None:
        if self._transport is None:
            raise NotConnectedError(f"{self.endpoint}: not connected (call connect() first)")
        self.stats["commands"] += 1
        if self._stale:
            await self._reconnect()
        try:
            await self._transport.write(encode_command(command))
        except NotConnectedError as exc:
            self._stale = True
            raise NotConnectedError(f"{exc}; {command!r} may not have reached the controller") from None
        if not check:
            return
        try:
            lines = await self._exchange("ERR?")
            code = int(lines[0].strip())
        except (ValueError, IndexError):
            self._stale = True
            raise ProtocolError(
                f"{self.endpoint}: unreadable ERR? reply after {command!r}; it may or may not have run"
            ) from None
        except DeviceError as exc:
            raise type(exc)(f"{exc}; {command!r} may or may not have run (not repeated)") from None
        if code:
            raise controller_error(code, command)

    async def error(self) -> int:
        """The controller's error code (``ERR?``; reading clears it)."""
        lines = await self.query("ERR?")
        try:
            return int(lines[0].strip())
        except (ValueError, IndexError):
            raise ProtocolError(f"{self.endpoint}: unreadable ERR? reply {lines!r}") from None

    async def send_now(self, command: str) -> None:
        """Write a command at once without waiting for the lock or reading anything (only for stops, which are safe to
        repeat); while another exchange reconnects, once the fresh connection is open."""
        if self._transport is None and self._reconnected is not None:
            await self._reconnected.wait()  # a query found the connection dropped and is opening a new one
        if self._transport is None:
            raise NotConnectedError(f"{self.endpoint}: not connected")
        if self._stale:
            await self._reconnect()
        try:
            await self._transport.write(encode_command(command))
        except NotConnectedError:
            await self._reconnect()
            await self._transport.write(encode_command(command))
