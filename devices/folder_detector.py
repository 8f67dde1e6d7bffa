"""Real panels whose vendor software writes frames into a folder (``folder:///data/panel?pattern=*.tif``).

Each new file is a frame once its size stops changing, delivered in write order: TIFF (one 2-D
page, via tifffile), or raw little-endian uint16 with the 32-byte ``ORBR`` header (see
:func:`write_raw_frame`) or headerless with ``rows=``, ``cols=`` and ``header_bytes=``.
"""

from __future__ import annotations

import asyncio
import fnmatch
import os
import struct
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from devices.base import DeviceInfo, Driver, Status
from devices.errors import DeviceError, DeviceTimeoutError, NotConnectedError, ProtocolError, UriError
from devices.frame_protocol import Frame
from devices.uri import checked_options, option_number, parse_uri
from orbitct.geometry import Panel

RAW_MAGIC = b"ORBR"
RAW_HEADER = struct.Struct(
    "<4sHHHHIQd"
)  # magic, version, header_len, rows, cols, frame number, ns timestamp(unused), exposure ms


def write_raw_frame(
    path: str | os.PathLike[str], data: NDArray[np.uint16], number: int, exposure_ms: float = 0.0
) -> None:
    """Write a raw frame with the small 'ORBR' header (what :class:`FolderWatchDetector` reads)."""
    rows, cols = data.shape
    head = RAW_HEADER.pack(RAW_MAGIC, 1, RAW_HEADER.size, rows, cols, number, time.time_ns(), exposure_ms)
    Path(path).write_bytes(head + np.ascontiguousarray(data, "<u2").tobytes())


def read_frame_file(
    path: Path, *, rows: int | None = None, cols: int | None = None, header_bytes: int = 0
) -> tuple[NDArray[np.uint16], dict[str, Any]]:
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
    except Exception as exc:  # noqa: BLE001 - tifffile raises many kinds
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
        raise ProtocolError(
            f"{path}: {len(raw)} bytes, expected {header_bytes} header + {2 * r * c} pixel bytes ({r}x{c})"
        )
    return np.frombuffer(raw, "<u2", offset=header_bytes).reshape(r, c).astype(np.uint16), meta


class FolderWatchDetector(Driver):
    """Frames that a vendor tool writes into a folder (``folder:///path?pattern=*.tif``), delivered in order."""

    OPTIONS = frozenset({"pattern", "poll_s", "timeout_s", "rows", "cols", "header_bytes", "pitch_mm", "settle_s"})

    def __init__(self, name: str = "detector", uri: str = "folder:///tmp/frames", **options: Any) -> None:
        super().__init__(name, uri)
        ep = parse_uri(uri)
        if ep.scheme != "folder":
            raise UriError(f"folder detector {name!r}: URI must be folder:///path?pattern=*.tif, got {uri!r}")
        opts = checked_options({**ep.params, **options}, self.OPTIONS, f"folder detector {name!r}")
        self.folder = Path(ep.path)
        self.pattern = str(opts.get("pattern", "*.tif"))
        self.poll_s = option_number(opts.get("poll_s", 0.05))
        self.timeout_s = option_number(opts.get("timeout_s", 10.0))
        self.settle_s = option_number(opts.get("settle_s", 0.02))
        self.rows = option_number(opts["rows"], int) if "rows" in opts else None
        self.cols = option_number(opts["cols"], int) if "cols" in opts else None
        self.header_bytes = option_number(opts.get("header_bytes", 0), int)
        self.pitch_mm = option_number(opts.get("pitch_mm", 0.0))
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
        """Nothing to release but what was attached to this driver."""
        await self._release()

    async def describe(self) -> DeviceInfo:
        """Folder, pattern and (once known) frame shape."""
        return DeviceInfo(
            self.name,
            "folder watch",
            str(self.folder),
            uri=self.uri,
            extra={"pattern": self.pattern, "shape": self._shape},
        )

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
                raise DeviceTimeoutError(
                    f"{self.name}: no new {self.pattern} file in {self.folder} (frame {self._number + 1} missing)"
                )
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
