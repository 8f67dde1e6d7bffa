"""The frame protocol (orbitct v1) that the simulated panel and the C-arm speak: what driver and twin share.

The client sends ASCII command lines ending in LF; every command gets one reply line,
``OK[ payload]`` or ``ERR <code> <text>``, except ``FRAME? <timeout_ms>`` whose success reply is
the header line ``FRAME <number> <timestamp_s> <rows> <cols> <kind> <meta_len> <data_len>``
followed by ``meta_len`` bytes of UTF-8 JSON metadata and ``data_len`` bytes of little-endian
uint16 pixels (row-major). Error codes: 1 unknown command, 2 not armed / wrong mode, 3 no frame
in time, 4 bad argument, 5 device error, 7 out of limits.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

DETECTOR_PORT = 5030
CARM_PORT = 5040
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


def encode_frame(frame: Frame) -> bytes:
    """Frame protocol bytes for ``frame`` (header line, JSON metadata, pixels)."""
    meta = json.dumps(frame.meta).encode()
    data = np.ascontiguousarray(frame.data, dtype="<u2").tobytes()
    rows, cols = frame.shape
    head = f"FRAME {frame.number} {frame.timestamp:.6f} {rows} {cols} {frame.kind} {len(meta)} {len(data)}\n"
    return head.encode() + meta + data


def parse_frame_header(line: str) -> tuple[int, float, int, int, str, int, int]:
    """Fields of a ``FRAME`` header line; ValueError when it is not one."""
    parts = line.split()
    if len(parts) != 8 or parts[0] != "FRAME" or parts[5] not in FRAME_KINDS:
        raise ValueError(line)
    number, ts, rows, cols = int(parts[1]), float(parts[2]), int(parts[3]), int(parts[4])
    meta_len, data_len = int(parts[6]), int(parts[7])
    if rows < 1 or cols < 1 or data_len != 2 * rows * cols or not 0 <= meta_len < 1 << 24:
        raise ValueError(line)
    return number, ts, rows, cols, parts[5], meta_len, data_len
