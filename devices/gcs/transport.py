"""Byte transports for GCS controllers: TCP (asyncio streams) and serial (pyserial, non-blocking)."""

from __future__ import annotations

import asyncio
import os
from typing import Protocol

from devices.errors import DeviceTimeoutError, NotConnectedError
from devices.gcs.framing import reply_complete
from devices.uri import Endpoint, option_number


class Transport(Protocol):
    """A connected byte stream to one controller."""

    description: str

    async def open(self) -> None:
        """Connect; raises :class:`NotConnectedError` naming the endpoint on failure."""

    async def write(self, data: bytes) -> None:
        """Send bytes."""

    async def read_reply(self, timeout_s: float) -> bytes:
        """Bytes up to the end of one complete GCS reply."""

    async def close(self) -> None:
        """Release the connection (idempotent)."""


class _StreamReplies:
    """Reply assembly shared by the transports: an asyncio reader plus a leftover buffer."""

    reader: asyncio.StreamReader | None = None
    description = ""

    def __init__(self) -> None:
        self._pending = b""

    async def read_reply(self, timeout_s: float) -> bytes:
        if self.reader is None:
            raise NotConnectedError(f"{self.description}: not connected")
        buf = self._pending
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            end = _reply_end(buf)
            if end:
                self._pending = buf[end:]
                return buf[:end]
            left = deadline - loop.time()
            if left <= 0:
                self._pending = b""
                raise DeviceTimeoutError(f"{self.description}: no complete reply within {timeout_s:g} s (got {buf!r})")
            try:
                async with asyncio.timeout(left):  # not wait_for: it can swallow a cancellation on 3.11
                    chunk = await self.reader.read(4096)
            except TimeoutError:
                continue
            except (ConnectionError, OSError) as exc:
                raise NotConnectedError(f"{self.description}: connection lost ({exc})") from None
            if not chunk:
                self._pending = b""
                raise NotConnectedError(f"{self.description}: connection closed by the controller")
            buf += chunk


def _reply_end(buf: bytes) -> int:
    """Length of the first complete reply in ``buf`` (0 if none yet)."""
    start = 0
    while True:
        i = buf.find(b"\n", start)
        if i < 0:
            return 0
        if reply_complete(buf[: i + 1]):
            return i + 1
        start = i + 1


class TcpTransport(_StreamReplies):
    """GCS over TCP (controllers listen on port 50000 by default)."""

    def __init__(self, host: str, port: int, *, connect_timeout_s: float = 3.0) -> None:
        super().__init__()
        self.host, self.port = host, port
        self.connect_timeout_s = connect_timeout_s
        self.description = f"tcp://{host}:{port}"
        self._writer: asyncio.StreamWriter | None = None

    async def open(self) -> None:
        try:
            async with asyncio.timeout(self.connect_timeout_s):
                self.reader, self._writer = await asyncio.open_connection(self.host, self.port)
        except (OSError, TimeoutError) as exc:
            raise NotConnectedError(f"{self.description}: cannot connect ({exc or 'timeout'})") from None
        sock = self._writer.get_extra_info("socket")
        if sock is not None:
            import socket

            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    async def write(self, data: bytes) -> None:
        if self._writer is None or self._writer.is_closing():
            raise NotConnectedError(f"{self.description}: not connected")
        try:
            self._writer.write(data)
            await self._writer.drain()
        except (ConnectionError, OSError) as exc:
            raise NotConnectedError(f"{self.description}: connection lost while sending ({exc})") from None

    async def close(self) -> None:
        writer, self._writer, self.reader = self._writer, None, None
        self._pending = b""
        if writer is not None:
            writer.close()
            try:
                await asyncio.wait_for(writer.wait_closed(), 1.0)
            except (TimeoutError, OSError):
                pass


class SerialTransport(_StreamReplies):
    """GCS over RS-232 with pyserial (8N1, no handshake), read without blocking the event loop."""

    def __init__(self, path: str, *, baud: int = 115200) -> None:
        super().__init__()
        self.path, self.baud = path, baud
        self.description = f"serial://{path}?baud={baud}"
        self._serial = None

    async def open(self) -> None:
        import serial

        try:
            port = serial.Serial(self.path, baudrate=self.baud, timeout=0, write_timeout=2.0)
        except (serial.SerialException, OSError) as exc:
            raise NotConnectedError(f"{self.description}: cannot open ({exc})") from None
        self._serial = port
        port.reset_input_buffer()  # replies meant for an earlier, abandoned exchange
        loop = asyncio.get_running_loop()
        self.reader = asyncio.StreamReader()
        fd = port.fileno()
        loop.add_reader(fd, self._on_readable, fd)

    def _on_readable(self, fd: int) -> None:
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if self.reader is None:
            return
        if data:
            self.reader.feed_data(data)
        else:
            asyncio.get_running_loop().remove_reader(fd)
            self.reader.feed_eof()

    async def write(self, data: bytes) -> None:
        if self._serial is None:
            raise NotConnectedError(f"{self.description}: not open")
        try:
            self._serial.write(data)
        except Exception as exc:  # noqa: BLE001 - pyserial raises SerialException / SerialTimeoutException / OSError
            raise NotConnectedError(f"{self.description}: write failed ({exc})") from None

    async def close(self) -> None:
        ser, self._serial, self.reader = self._serial, None, None
        self._pending = b""
        if ser is not None:
            try:
                asyncio.get_running_loop().remove_reader(ser.fileno())
            except (ValueError, OSError):
                pass
            ser.close()


def transport_for(endpoint: Endpoint) -> Transport:
    """The transport for a ``tcp://`` or ``serial://`` endpoint."""
    if endpoint.scheme == "tcp":
        assert endpoint.port is not None
        return TcpTransport(
            endpoint.host, endpoint.port, connect_timeout_s=option_number(endpoint.params.get("connect_timeout", 3.0))
        )
    if endpoint.scheme == "serial":
        return SerialTransport(endpoint.path, baud=int(endpoint.params.get("baud", 115200)))
    from devices.errors import UriError

    raise UriError(
        f"GCS controllers connect over tcp://host:port or serial:///dev/ttyX?baud=N, not {endpoint.scheme}://"
    )
