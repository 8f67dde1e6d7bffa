"""Flat-panel driver over the frame protocol (:mod:`devices.frame_protocol`), with its TCP client.

A missing frame is a :class:`~devices.errors.DeviceTimeoutError` naming its number; nothing is
re-triggered automatically. Panels whose vendor software writes files use
:class:`devices.folder_detector.FolderWatchDetector` instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from typing import Any

import numpy as np

from devices.base import DeviceInfo, Driver, Status
from devices.errors import (
    ControllerError,
    DeviceError,
    DeviceTimeoutError,
    NotConnectedError,
    OutOfLimitsError,
    ProtocolError,
    UriError,
)
from devices.frame_protocol import DETECTOR_PORT, ERR_LIMITS, ERR_NO_FRAME, Frame, parse_frame_header
from devices.uri import Endpoint, checked_options, option_number, parse_uri
from orbitct.geometry import Panel


def _error_for(code: int, text: str, command: str) -> DeviceError:
    if code == ERR_NO_FRAME:
        return DeviceTimeoutError(f"{text} ({command!r})")
    if code == ERR_LIMITS:
        return OutOfLimitsError(f"{text}; nothing moved")
    return ControllerError(code, text, command)


class FrameLink:
    """TCP client of the frame protocol with timeouts, garble detection and reconnect for safe commands."""

    def __init__(self, name: str, host: str, port: int, timeout_s: float) -> None:
        self.name, self.host, self.port, self.timeout_s = name, host, port, timeout_s
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._lock = asyncio.Lock()
        self._opened = False

    async def open(self) -> None:
        """Connect (again)."""
        await self._drop()
        try:
            async with asyncio.timeout(self.timeout_s):  # unlike wait_for, never swallows a cancellation
                self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        except (TimeoutError, OSError) as exc:
            raise NotConnectedError(
                f"{self.name}: cannot connect to {self.host}:{self.port} ({exc or 'timeout'})"
            ) from None
        self._opened = True

    async def _drop(self) -> None:
        if self._writer is not None:
            self._writer.close()
            with contextlib.suppress(Exception):
                await self._writer.wait_closed()
        self._reader = self._writer = None

    async def close(self) -> None:
        """Disconnect (idempotent)."""
        self._opened = False
        await self._drop()

    async def command(self, line: str, *, retry: bool = True, wait_s: float = 0.0) -> str:
        """Send one command; return the payload after ``OK``. Safe commands reconnect and repeat once."""
        async with self._lock:
            for attempt in range(2 if retry else 1):
                try:
                    return await self._roundtrip(line, wait_s, frame=False)  # type: ignore[return-value]
                except (_ReplyTimeout, NotConnectedError, ProtocolError):
                    await self._drop()  # the stream is out of step or gone
                    if not retry or attempt == 1 or not self._opened:
                        raise
                    await self.open()
        raise AssertionError("unreachable")

    async def urgent(self, line: str) -> str:
        """Send one command on a connection of its own, not queued behind a long wait (e.g. STOP during a frame wait)."""
        side = FrameLink(self.name, self.host, self.port, self.timeout_s)
        await side.open()
        try:
            return await side.command(line, retry=False)
        finally:
            await side.close()

    async def frame(self, timeout_s: float) -> Frame:
        """Ask for the next frame, waiting up to ``timeout_s`` on the device; never repeated."""
        async with self._lock:
            try:
                return await self._roundtrip(f"FRAME? {int(timeout_s * 1000)}", timeout_s, frame=True)  # type: ignore[return-value]
            except (NotConnectedError, ProtocolError, _ReplyTimeout):
                await self._drop()
                raise

    async def _roundtrip(self, line: str, wait_s: float, *, frame: bool) -> str | Frame:
        try:
            return await self._exchange(line, wait_s, frame=frame)
        except asyncio.CancelledError:
            self._abandon()  # a reply may still be in flight: the next command starts on a fresh connection
            raise

    def _abandon(self) -> None:
        if self._writer is not None:
            self._writer.transport.abort()
        self._reader = self._writer = None

    async def _exchange(self, line: str, wait_s: float, *, frame: bool) -> str | Frame:
        if self._writer is None or self._reader is None:
            if not self._opened:
                raise NotConnectedError(f"{self.name}: not connected")
            await self.open()
        assert self._reader is not None and self._writer is not None
        try:
            self._writer.write(line.encode("latin-1") + b"\n")
            await self._writer.drain()
            async with asyncio.timeout(self.timeout_s + wait_s):
                raw = await self._reader.readline()
        except TimeoutError:
            raise _ReplyTimeout(f"{self.name}: no reply to {line!r} within {self.timeout_s + wait_s:g} s") from None
        except (ConnectionError, OSError):
            raise NotConnectedError(f"{self.name}: connection lost during {line!r}") from None
        if not raw.endswith(b"\n"):
            raise NotConnectedError(f"{self.name}: connection closed by the device during {line!r}")
        text = raw.decode("latin-1").rstrip("\r\n")
        if text == "OK" or text.startswith("OK "):
            if frame:
                raise ProtocolError(f"{self.name}: expected a frame after {line!r}, got {text[:60]!r}")
            return text[3:]
        if text.startswith("ERR "):
            parts = text.split(" ", 2)
            if len(parts) == 3 and parts[1].isdigit():
                raise _error_for(int(parts[1]), f"{self.name}: {parts[2]}", line)
        if frame and text.startswith("FRAME "):
            return await self._read_frame_body(text, line)
        raise ProtocolError(f"{self.name}: garbled reply to {line!r}: {text[:60]!r}")

    async def _read_frame_body(self, header: str, line: str) -> Frame:
        assert self._reader is not None
        try:
            number, ts, rows, cols, kind, meta_len, data_len = parse_frame_header(header)
        except ValueError:
            raise ProtocolError(f"{self.name}: garbled frame header {header[:80]!r}") from None
        try:
            async with asyncio.timeout(self.timeout_s + 1.0):
                body = await self._reader.readexactly(meta_len + data_len)
        except asyncio.IncompleteReadError:
            raise NotConnectedError(f"{self.name}: connection closed in the middle of frame {number}") from None
        except TimeoutError:
            raise _ReplyTimeout(
                f"{self.name}: frame {number} data did not arrive within {self.timeout_s + 1:g} s"
            ) from None
        try:
            meta = json.loads(body[:meta_len].decode()) if meta_len else {}
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise ProtocolError(f"{self.name}: garbled metadata of frame {number}") from None
        data = np.frombuffer(body[meta_len:], dtype="<u2").reshape(rows, cols).astype(np.uint16)
        return Frame(data, number, ts, kind, meta)


class _ReplyTimeout(DeviceTimeoutError):
    """No reply in time (the stream is then out of step and gets reopened)."""


class Detector(Driver):
    """Driver of a flat panel speaking the frame protocol (``tcp://host:port``)."""

    OPTIONS = frozenset({"binning", "trigger", "timeout_s", "frame_timeout_s", "monitor"})
    default_port = DETECTOR_PORT
    kind = "detector"

    def __init__(self, name: str = "detector", uri: str = "tcp://127.0.0.1:5030", **options: Any) -> None:
        super().__init__(name, uri)
        self.endpoint: Endpoint = parse_uri(uri, default_port=self.default_port)
        if self.endpoint.scheme != "tcp":
            raise UriError(f"{self.kind} {name!r}: URI must be tcp://host:port, got {uri!r}")
        opts = checked_options({**self.endpoint.params, **options}, self.OPTIONS, f"{self.kind} {name!r}")
        self.timeout_s = option_number(opts.pop("timeout_s", 2.0))
        self.frame_timeout_s = option_number(opts.pop("frame_timeout_s", 10.0))
        self.binning = option_number(opts.pop("binning", 1), int)
        self.trigger_mode = str(opts.pop("trigger", "software")).lower()
        if self.trigger_mode not in ("software", "xray"):
            raise UriError(f"detector {name!r}: trigger must be 'software' or 'xray', got {self.trigger_mode!r}")
        # a second connection that only reads and stops (a safety monitor): it leaves binning, trigger and arming alone
        self.monitor = bool(option_number(opts.pop("monitor", 0), int))
        self._extra = opts  # options of subclasses
        self._link: FrameLink | None = None
        self._geometry: Panel | None = None
        self._last_number: int | None = None

    # ------------------------------------------------------------- connection
    async def connect(self) -> None:
        """Connect, and apply binning and trigger mode."""
        self._link = FrameLink(
            self.name, self.endpoint.host, int(self.endpoint.port or self.default_port), self.timeout_s
        )
        await self._link.open()
        if self.monitor:
            await self._read_shape()
            return
        await self.set_binning(self.binning)
        await self.set_trigger(self.trigger_mode)

    async def close(self) -> None:
        """Disconnect and release what was attached to this driver (idempotent)."""
        if self._link is not None:
            await self._link.close()
            self._link = None
        await self._release()

    async def __aenter__(self) -> Detector:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _l(self) -> FrameLink:
        if self._link is None:
            raise NotConnectedError(f"{self.name}: not connected (call connect() first)")
        return self._link

    # ------------------------------------------------------------------ API
    @property
    def shape(self) -> tuple[int, int]:
        """Frame shape ``(rows, cols)`` after binning."""
        return self.geometry.shape

    @property
    def geometry(self) -> Panel:
        """Pixel grid after binning (pitch scaled)."""
        if self._geometry is None:
            raise NotConnectedError(f"{self.name}: frame shape unknown until connected")
        return self._geometry

    async def describe(self) -> DeviceInfo:
        """Model, serial, firmware, panel size and pitch."""
        model, serial, firmware = (await self._l().command("IDN?")).split(",")[:3]
        g = self.geometry
        return DeviceInfo(
            self.name,
            model,
            serial,
            firmware,
            uri=self.uri,
            extra={
                "rows": g.rows,
                "cols": g.cols,
                "pitch_mm": g.pitch_mm,
                "binning": self.binning,
                "trigger": self.trigger_mode,
            },
        )

    async def read(self) -> dict[str, Any]:
        """Armed flag, trigger mode, frames taken and queued, shape."""
        out: dict[str, Any] = {}
        for item in (await self._l().command("STATE?")).split():
            key, _, value = item.partition("=")
            out[key] = int(value) if value.lstrip("-").isdigit() else value
        out["shape"] = self.shape
        return out

    async def set_binning(self, factor: int) -> None:
        """Bin ``factor x factor`` pixels (1, 2 or 4)."""
        await self._l().command(f"BIN {int(factor)}")
        await self._read_shape()

    async def _read_shape(self) -> None:
        rows, cols, pc, pr, b = (await self._l().command("SHAPE?")).split()
        self.binning = int(b)
        self._geometry = Panel(int(rows), int(cols), float(pc), float(pr))

    async def set_trigger(self, mode: str) -> None:
        """``'software'`` (``trigger()``) or ``'xray'`` (a frame per generator exposure)."""
        await self._l().command(f"TRIGMODE {mode.upper()}")
        self.trigger_mode = mode.lower()

    async def arm(self) -> None:
        """Accept triggers from now on (frames already queued are discarded)."""
        await self._l().command("ARM")

    async def disarm(self) -> None:
        """Stop accepting triggers."""
        await self._l().command("DISARM")

    def trigger(self) -> Status[Frame]:
        """Software trigger: take one projection now and return it."""
        return Status(f"{self.name}.trigger", self._take("TRIG"))

    async def _take(self, command: str) -> Frame:
        reply = (await self._l().command(command, retry=False)).strip()
        expected = int(reply) if reply.isdigit() else None
        try:
            return await self.read_frame()
        except DeviceTimeoutError as exc:
            if expected is None:
                raise
            self._last_number = expected  # reported here; not again as a gap
            raise DeviceTimeoutError(f"{self.name}: frame {expected} missing ({exc}); not re-triggered") from None

    async def read_frame(self, timeout_s: float | None = None) -> Frame:
        """The next frame; ``DeviceTimeoutError`` if none arrives (a missing frame is named, never re-triggered)."""
        frame = await self._l().frame(self.frame_timeout_s if timeout_s is None else timeout_s)
        last = self._last_number
        self._last_number = frame.number
        if last is not None and frame.number > last + 1:
            missing = ", ".join(str(n) for n in range(last + 1, frame.number))
            raise DeviceTimeoutError(f"{self.name}: frame(s) {missing} missing (received frame {frame.number})")
        return frame

    async def acquire_dark(self, n: int) -> list[Frame]:
        """``n`` dark frames (no X-rays)."""
        return [await self._take("DARK") for _ in range(int(n))]

    async def acquire_flat(self, n: int) -> list[Frame]:
        """``n`` flat (open beam) frames at the current X-ray settings."""
        return [await self._take("FLAT") for _ in range(int(n))]
