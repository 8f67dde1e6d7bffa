"""GCS 2.0 framing: how commands and replies look on the wire (8-bit text, LF-terminated).

A command is ``NAME args LF``; the single-character commands ``#5``, ``#7`` and
``#24`` are the bare bytes 5, 7 and 24. A reply of several lines ends every line
but the last with ``" \\n"``; the last line ends with ``"\\n"`` alone.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from devices.errors import ProtocolError

ENCODING = "cp1252"  # PI's controller code page: 8-bit text, one byte per character
SINGLE_CHAR: dict[str, bytes] = {"#5": b"\x05", "#7": b"\x07", "#24": b"\x18"}
READY, BUSY = "\xb1", "\xb0"  # #7 replies: controller ready / busy (e.g. referencing)


def encode_command(command: str) -> bytes:
    """Bytes for one command: single-character commands bare, all others with LF."""
    if command in SINGLE_CHAR:
        return SINGLE_CHAR[command]
    if "\n" in command:
        raise ProtocolError(f"GCS command {command!r} must be one line")
    return (command + "\n").encode(ENCODING)


def reply_complete(buf: bytes) -> bool:
    """Whether ``buf`` holds a whole reply: ends in LF not preceded by a space."""
    return buf.endswith(b"\n") and not buf.endswith(b" \n")


def join_reply(lines: Iterable[str]) -> bytes:
    """Frame reply lines: ``" \\n"`` after every line but the last, ``"\\n"`` after the last."""
    lines = list(lines)
    if not lines:
        return b""
    return (" \n".join(lines) + "\n").encode(ENCODING)


def split_reply(raw: bytes) -> list[str]:
    """Lines of a complete reply (framing checked; continuation spaces removed)."""
    if not reply_complete(raw):
        raise ProtocolError(f"incomplete GCS reply {raw!r}")
    text = raw.decode(ENCODING)
    lines = text[:-1].split("\n")
    for line in lines[:-1]:
        if not line.endswith(" "):
            raise ProtocolError(f"GCS reply line {line!r} lacks the continuation space")
    return [ln[:-1] if i < len(lines) - 1 else ln for i, ln in enumerate(lines)]


def format_value(value: float | int | str | bool) -> str:
    """A value as the controller writes it."""
    if hasattr(value, "item"):  # numpy scalars
        value = value.item()
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:.6f}"
    return str(value)


def axis_lines(values: Mapping[str, float | int | bool]) -> list[str]:
    """Reply lines ``axis=value`` in the given order."""
    return [f"{k}={format_value(v)}" for k, v in values.items()]


def parse_axis_values(lines: Iterable[str], command: str = "") -> dict[str, float]:
    """Parse ``axis=value`` lines into floats; garbled lines raise :class:`ProtocolError`."""
    out: dict[str, float] = {}
    for line in lines:
        key, sep, val = line.partition("=")
        key = key.strip()
        if not sep or not key or " " in key:
            raise ProtocolError(f"reply to {command!r}: expected 'axis=value', got {line!r}")
        try:
            out[key] = float(val.strip())
        except ValueError:
            raise ProtocolError(f"reply to {command!r}: {val.strip()!r} is not a number (line {line!r})") from None
    return out


def format_command(name: str, args: Mapping[str, float | int | bool] | Iterable[str] = ()) -> str:
    """``NAME a1 v1 a2 v2`` for axis/value pairs, or ``NAME a1 a2`` for a list of axes."""
    if isinstance(args, Mapping):
        parts = [f"{k} {format_value(v if isinstance(v, (bool, str)) else float(v))}" for k, v in args.items()]
    else:
        parts = list(args)
    return " ".join([name, *parts])
