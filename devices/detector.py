"""Frame sources: the simulated flat panel (frame protocol over TCP) and a folder watcher for real panels.

Frame protocol (orbitct v1, spoken by the detector and C-arm twins): the client sends ASCII
command lines ending in LF; every command gets one reply line, ``OK[ payload]`` or
``ERR <code> <text>``, except ``FRAME? <timeout_ms>`` whose success reply is the header line
``FRAME <number> <timestamp_s> <rows> <cols> <kind> <meta_len> <data_len>`` followed by
``meta_len`` bytes of UTF-8 JSON metadata and ``data_len`` bytes of little-endian uint16 pixels
(row-major). Error codes: 1 unknown command, 2 not armed / wrong mode, 3 no frame in time,
4 bad argument, 5 device error, 7 out of limits.
"""

from __future__ import annotations

import asyncio
import contextlib
import fnmatch
import json
import os
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from devices.base import DeviceInfo, Status
from devices.errors import (
    ControllerError,
    DeviceError,
    DeviceTimeoutError,
    NotConnectedError,
    OutOfLimitsError,
    ProtocolError,
    UriError,
)
from devices.uri import Endpoint, parse_uri
from orbitct.geometry import Panel

PANEL_MM = 427.0
DEFAULT_PIXELS = 768
DETECTOR_PORT = 5030
ERR_UNKNOWN, ERR_NOT_ARMED, ERR_NO_FRAME, ERR_BAD_ARG, ERR_DEVICE, ERR_LIMITS = 1, 2, 3, 4, 5, 7
FRAME_KINDS = ("projection", "dark", "flat")


@dataclass
class Frame:
    """One detector frame: uint16 counts, frame number, timestamp (unix s), kind and metadata."""

    data: NDArray[np.uint16]
    number: int
    timestamp: float
    kind: str = "projection"
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return (int(self.data.shape[0]), int(self.data.shape[1]))


@runtime_checkable
class FrameSource(Protocol):
    """What acquisition needs from any detector."""

    name: str

    @property
    def shape(self) -> tuple[int, int]:
        """Frame shape ``(rows, cols)`` after binning."""

    async def arm(self) -> None:
        """Get ready to deliver the next frames."""

    def trigger(self) -> Status[Frame]:
        """Take one frame now (software trigger) and return it."""

    async def read_frame(self, timeout_s: float | None = None) -> Frame:
        """The next frame (e.g. one triggered by the generator's exposure)."""

    async def acquire_dark(self, n: int) -> list[Frame]:
        """``n`` frames without X-rays."""

    async def acquire_flat(self, n: int) -> list[Frame]:
        """``n`` open-beam frames."""


def encode_frame(frame: Frame) -> bytes:
    """Frame protocol bytes for ``frame`` (header line, JSON metadata, pixels)."""
    meta = json.dumps(frame.meta).encode()
    data = np.ascontiguousarray(frame.data, dtype="<u2").tobytes()
    rows, cols = frame.shape
    head = f"FRAME {frame.number} {frame.timestamp:.6f} {rows} {cols} {frame.kind} {len(meta)} {len(data)}\n"
    return head.encode() + meta + data


def _parse_frame_header(line: str) -> tuple[int, float, int, int, str, int, int]:
    parts = line.split()
    if len(parts) != 8 or parts[0] != "FRAME" or parts[5] not in FRAME_KINDS:
        raise ValueError(line)
    number, ts, rows, cols = int(parts[1]), float(parts[2]), int(parts[3]), int(parts[4])
    meta_len, data_len = int(parts[6]), int(parts[7])
    if rows < 1 or cols < 1 or data_len != 2 * rows * cols or not 0 <= meta_len < 1 << 24:
        raise ValueError(line)
    return number, ts, rows, cols, parts[5], meta_len, data_len


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
        except (OSError, asyncio.TimeoutError) as exc:
            raise NotConnectedError(f"{self.name}: cannot connect to {self.host}:{self.port} ({exc or 'timeout'})") from None
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
        except asyncio.TimeoutError:
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
            number, ts, rows, cols, kind, meta_len, data_len = _parse_frame_header(header)
        except ValueError:
            raise ProtocolError(f"{self.name}: garbled frame header {header[:80]!r}") from None
        try:
            async with asyncio.timeout(self.timeout_s + 1.0):
                body = await self._reader.readexactly(meta_len + data_len)
        except asyncio.IncompleteReadError:
            raise NotConnectedError(f"{self.name}: connection closed in the middle of frame {number}") from None
        except asyncio.TimeoutError:
            raise _ReplyTimeout(f"{self.name}: frame {number} data did not arrive within {self.timeout_s + 1:g} s") from None
        try:
            meta = json.loads(body[:meta_len].decode()) if meta_len else {}
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise ProtocolError(f"{self.name}: garbled metadata of frame {number}") from None
        data = np.frombuffer(body[meta_len:], dtype="<u2").reshape(rows, cols).astype(np.uint16)
        return Frame(data, number, ts, kind, meta)


class _ReplyTimeout(DeviceTimeoutError):
    """No reply in time (the stream is then out of step and gets reopened)."""


def panel_options(params: dict[str, Any], allowed: set[str], what: str) -> dict[str, Any]:
    """Check option names against ``allowed``; raises UriError naming the allowed ones."""
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise UriError(f"{what}: unknown option(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}")
    return params


def _num(v: Any, cast: type = float) -> Any:
    try:
        return cast(v)
    except (TypeError, ValueError):
        raise UriError(f"option value {v!r} is not a number") from None


class Detector:
    """Driver of the simulated flat panel (``sim://world`` or ``tcp://host:port``, frame protocol)."""

    OPTIONS = {"rows", "cols", "binning", "trigger", "timeout_s", "frame_timeout_s", "sad_mm", "sdd_mm", "seed", "phantom", "panel_mm", "pitch_mm", "detector_model"}
    default_port = DETECTOR_PORT
    kind = "detector"

    def __new__(cls, name: str = "detector", uri: str = "sim://bench", **options: Any) -> Any:
        """``folder://`` URIs give a :class:`FolderWatchDetector` (so configs can name any panel here)."""
        if cls is Detector and str(uri).lower().startswith("folder:"):
            return FolderWatchDetector(name, uri, **options)
        return super().__new__(cls)

    def __init__(self, name: str = "detector", uri: str = "sim://bench", **options: Any) -> None:
        self.name, self.uri = name, uri
        self.endpoint: Endpoint = parse_uri(uri, default_port=self.default_port)
        if self.endpoint.scheme not in ("sim", "tcp"):
            raise UriError(f"{self.kind} {name!r}: URI must be sim://<world> or tcp://host:port, got {uri!r}")
        opts = panel_options({**self.endpoint.params, **options}, self.OPTIONS, f"{self.kind} {name!r}")
        self.timeout_s = _num(opts.pop("timeout_s", 2.0))
        self.frame_timeout_s = _num(opts.pop("frame_timeout_s", 10.0))
        self.binning = _num(opts.pop("binning", 1), int)
        self.trigger_mode = str(opts.pop("trigger", "software")).lower()
        if self.trigger_mode not in ("software", "xray"):
            raise UriError(f"detector {name!r}: trigger must be 'software' or 'xray', got {self.trigger_mode!r}")
        self._twin_options = opts
        self.twin: Any = None
        self._twin_thread: Any = None
        self._link: FrameLink | None = None
        self._geometry: Panel | None = None
        self._last_number: int | None = None

    # ------------------------------------------------------------- connection
    async def connect(self) -> None:
        """Start the in-process twin for ``sim://``, connect, and apply binning and trigger mode."""
        host, port = self.endpoint.host, self.endpoint.port
        if self.endpoint.scheme == "sim":
            if self._twin_thread is None:
                from devices.twins.xray import TwinThread

                self.twin = self._make_twin()
                self._twin_thread = TwinThread(self.twin)
            host, port = "127.0.0.1", self._twin_thread.port
        self._link = FrameLink(self.name, host, int(port or self.default_port), self.timeout_s)
        await self._link.open()
        await self.set_binning(self.binning)
        await self.set_trigger(self.trigger_mode)

    def _make_twin(self) -> Any:
        from devices.twins.detector import DetectorTwin
        from devices.twins.world import get_world

        return DetectorTwin(get_world(self.endpoint.host or "bench"), **self._twin_options)

    async def close(self) -> None:
        """Disconnect and stop an in-process twin (idempotent)."""
        if self._link is not None:
            await self._link.close()
            self._link = None
        if self._twin_thread is not None:
            await asyncio.get_running_loop().run_in_executor(None, self._twin_thread.stop)
            self._twin_thread = None

    async def __aenter__(self) -> "Detector":
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
            self.name, model, serial, firmware, uri=self.uri,
            extra={"rows": g.rows, "cols": g.cols, "pitch_mm": g.pitch_mm, "binning": self.binning, "trigger": self.trigger_mode},
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


# --------------------------------------------------------------------------- folder watch
RAW_MAGIC = b"ORBR"
RAW_HEADER = struct.Struct("<4sHHHHIQd")  # magic, version, header_len, rows, cols, frame number, ns timestamp(unused), exposure ms


def write_raw_frame(path: str | os.PathLike[str], data: NDArray[np.uint16], number: int, exposure_ms: float = 0.0) -> None:
    """Write a raw frame with the small 'ORBR' header (what :class:`FolderWatchDetector` reads)."""
    rows, cols = data.shape
    head = RAW_HEADER.pack(RAW_MAGIC, 1, RAW_HEADER.size, rows, cols, number, time.time_ns(), exposure_ms)
    Path(path).write_bytes(head + np.ascontiguousarray(data, "<u2").tobytes())


def read_frame_file(path: Path, *, rows: int | None = None, cols: int | None = None, header_bytes: int = 0) -> tuple[NDArray[np.uint16], dict[str, Any]]:
    """Pixels and metadata of one TIFF or raw frame file; ProtocolError if it cannot be read."""
    suffix = path.suffix.lower()
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile

            data = tifffile.imread(path)
            if data.ndim != 2:
                raise ProtocolError(f"{path}: expected one 2-D frame, got shape {data.shape}")
            return np.asarray(data).astype(np.uint16, copy=False), {}
        raw = path.read_bytes()
    except ProtocolError:
        raise
    except Exception as exc:  # tifffile raises many kinds
        raise ProtocolError(f"{path}: cannot read frame ({exc})") from None
    if raw[:4] == RAW_MAGIC and len(raw) >= RAW_HEADER.size:
        _, _, hlen, r, c, number, _, exposure_ms = RAW_HEADER.unpack_from(raw)
        meta: dict[str, Any] = {"file_frame_number": number, "exposure_ms": exposure_ms}
        header_bytes = hlen
    elif rows and cols:
        r, c, meta = rows, cols, {}
    else:
        raise ProtocolError(f"{path}: raw file without an 'ORBR' header; give rows=, cols= (and header_bytes=)")
    if len(raw) != header_bytes + 2 * r * c:
        raise ProtocolError(f"{path}: {len(raw)} bytes, expected {header_bytes} header + {2 * r * c} pixel bytes ({r}x{c})")
    return np.frombuffer(raw, "<u2", offset=header_bytes).reshape(r, c).astype(np.uint16), meta


class FolderWatchDetector:
    """Frames that a vendor tool writes into a folder (``folder:///path?pattern=*.tif``), delivered in order."""

    OPTIONS = {"pattern", "poll_s", "timeout_s", "rows", "cols", "header_bytes", "pitch_mm", "settle_s"}

    def __init__(self, name: str = "detector", uri: str = "folder:///tmp/frames", **options: Any) -> None:
        self.name, self.uri = name, uri
        ep = parse_uri(uri)
        if ep.scheme != "folder":
            raise UriError(f"folder detector {name!r}: URI must be folder:///path?pattern=*.tif, got {uri!r}")
        opts = panel_options({**ep.params, **options}, self.OPTIONS, f"folder detector {name!r}")
        self.folder = Path(ep.path)
        self.pattern = str(opts.get("pattern", "*.tif"))
        self.poll_s = _num(opts.get("poll_s", 0.05))
        self.timeout_s = _num(opts.get("timeout_s", 10.0))
        self.settle_s = _num(opts.get("settle_s", 0.02))
        self.rows = _num(opts["rows"], int) if "rows" in opts else None
        self.cols = _num(opts["cols"], int) if "cols" in opts else None
        self.header_bytes = _num(opts.get("header_bytes", 0), int)
        self.pitch_mm = _num(opts.get("pitch_mm", 0.0))
        self._seen: set[str] = set()
        self._number = 0
        self._shape: tuple[int, int] | None = (self.rows, self.cols) if self.rows and self.cols else None
        self._next_kind = "projection"

    async def connect(self) -> None:
        """Check the folder exists; files already there are not frames of this session."""
        if not self.folder.is_dir():
            raise NotConnectedError(f"{self.name}: folder {self.folder} does not exist")
        await self.arm()

    async def close(self) -> None:
        """Nothing to release."""

    async def describe(self) -> DeviceInfo:
        """Folder, pattern and (once known) frame shape."""
        return DeviceInfo(self.name, "folder watch", str(self.folder), uri=self.uri, extra={"pattern": self.pattern, "shape": self._shape})

    async def read(self) -> dict[str, Any]:
        """Frames delivered, files waiting, frame shape."""
        return {"frames": self._number, "waiting": len(self._new_files()), "shape": self._shape}

    @property
    def shape(self) -> tuple[int, int]:
        """Frame shape ``(rows, cols)`` (known from options or the first frame)."""
        if self._shape is None:
            raise DeviceError(f"{self.name}: frame shape unknown until the first frame (or give rows=, cols=)")
        return self._shape

    @property
    def geometry(self) -> Panel:
        """Pixel grid (needs the ``pitch_mm`` option and a known shape)."""
        if not self.pitch_mm:
            raise DeviceError(f"{self.name}: pixel pitch unknown; give the pitch_mm option")
        rows, cols = self.shape
        return Panel(rows, cols, self.pitch_mm, self.pitch_mm)

    async def set_trigger(self, mode: str) -> None:
        """Accepted for either mode: the vendor tool decides what starts a frame."""
        if mode.lower() not in ("software", "xray"):
            raise DeviceError(f"{self.name}: trigger must be 'software' or 'xray', got {mode!r}")

    async def set_binning(self, factor: int) -> None:
        """Binning is set in the vendor tool; only 1 (as delivered) is accepted here."""
        if int(factor) != 1:
            raise DeviceError(f"{self.name}: set binning {factor} in the vendor software; files are used as written")

    async def arm(self) -> None:
        """Ignore every file already in the folder; deliver only files written from now on."""
        self._seen = {p.name for p in self._matching()}

    def _matching(self) -> list[Path]:
        try:
            names = os.listdir(self.folder)
        except OSError as exc:
            raise NotConnectedError(f"{self.name}: cannot list {self.folder} ({exc})") from None
        return [self.folder / n for n in names if fnmatch.fnmatch(n, self.pattern)]

    def _new_files(self) -> list[Path]:
        files = [p for p in self._matching() if p.name not in self._seen]
        return sorted(files, key=lambda p: (p.stat().st_mtime_ns, p.name))

    async def read_frame(self, timeout_s: float | None = None) -> Frame:
        """The oldest new file once its size stopped changing; DeviceTimeoutError if none arrives."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            files = self._new_files()
            if files:
                path = files[0]
                size = path.stat().st_size
                await asyncio.sleep(self.settle_s)
                if path.stat().st_size == size and size > 0:
                    self._seen.add(path.name)
                    data, meta = read_frame_file(path, rows=self.rows, cols=self.cols, header_bytes=self.header_bytes)
                    if self._shape is not None and data.shape != self._shape:
                        raise ProtocolError(f"{self.name}: {path.name} has shape {data.shape}, expected {self._shape}")
                    self._shape = (int(data.shape[0]), int(data.shape[1]))
                    self._number += 1
                    meta["file"] = str(path)
                    kind, self._next_kind = self._next_kind, "projection"
                    return Frame(data, self._number, path.stat().st_mtime, kind, meta)
                continue
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(f"{self.name}: no new {self.pattern} file in {self.folder} (frame {self._number + 1} missing)")
            await asyncio.sleep(self.poll_s)

    def trigger(self) -> Status[Frame]:
        """Wait for the next file (the vendor tool is triggered by the generator or its own UI)."""
        return Status(f"{self.name}.trigger", self.read_frame())

    async def _frames(self, n: int, kind: str) -> list[Frame]:
        out = []
        for _ in range(int(n)):
            self._next_kind = kind
            out.append(await self.read_frame())
        return out

    async def acquire_dark(self, n: int) -> list[Frame]:
        """The next ``n`` files, labelled dark (take them with X-rays off in the vendor tool)."""
        return await self._frames(n, "dark")

    async def acquire_flat(self, n: int) -> list[Frame]:
        """The next ``n`` files, labelled flat (open beam in the vendor tool)."""
        return await self._frames(n, "flat")
