"""The emergency-stop latch: set by any stop, cleared only by an operator's deliberate reset.

The latch lives in ``<data_dir>/estop.json`` (so it survives a restart: a bench stopped before a
power cut is still stopped after it) and, for the processes of one running service, in a shared
flag that the web server, the guard and the rig process read without touching the disk. While
it is set, scans, moves and referencing are refused everywhere.
"""

from __future__ import annotations

import ctypes
import json
import multiprocessing as mp
import threading
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Protocol

from orbitct_app.service.core.jsonfile import write_json_atomically

FILE_NAME = "estop.json"
HISTORY = 50  # stops and resets kept in the file


class Flag(Protocol):
    """A flag shared between processes (:class:`SharedFlag`) or within one (``threading.Event``)."""

    def is_set(self) -> bool: ...

    def set(self) -> None: ...

    def clear(self) -> None: ...


class SharedFlag:
    """One byte of shared memory, without a lock: a process killed at any instant cannot leave it blocked.

    (A ``multiprocessing.Event`` takes a lock even to read; a process killed while holding it would
    freeze every other process that reads the latch, the guard included.)
    """

    def __init__(self, context: Any = None) -> None:
        self._value = (context or mp.get_context("spawn")).RawValue(ctypes.c_ubyte, 0)

    def is_set(self) -> bool:
        """Whether the flag is set."""
        return bool(self._value.value)

    def set(self) -> None:
        """Set the flag."""
        self._value.value = 1

    def clear(self) -> None:
        """Clear the flag."""
        self._value.value = 0

    def wait(self, timeout_s: float, poll_s: float = 0.005) -> bool:
        """Whether the flag is set within ``timeout_s`` (polled)."""
        deadline = time.monotonic() + timeout_s
        while not self.is_set():
            if time.monotonic() >= deadline:
                return False
            time.sleep(poll_s)
        return True


class NotLatchedError(Exception):
    """A reset asked for while no stop is latched."""


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


class StopLatch:
    """The latch of one bench: ``engage`` on any stop, ``reset`` by an operator; ``state`` for replies."""

    def __init__(self, data_dir: Path, flag: Flag | None = None) -> None:
        self.path = Path(data_dir) / FILE_NAME
        self.flag: Flag = flag if flag is not None else threading.Event()
        self._lock = threading.Lock()
        if self._read().get("latched"):
            self.flag.set()

    @property
    def latched(self) -> bool:
        """Whether a stop is latched (no file access)."""
        return self.flag.is_set()

    def _read(self) -> dict[str, Any]:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            return data if isinstance(data, dict) else {}
        except (OSError, ValueError):
            return {}

    def _write(self, data: dict[str, Any]) -> None:
        write_json_atomically(self.path, data)

    def engage(self, by: str, reason: str, via: str) -> dict[str, Any]:
        """Latch (the file, then the flag the other processes watch); a second stop keeps the first one's time and author."""
        with self._lock:
            data = self._read()
            event = {"event": "stop", "utc": _now(), "by": by, "reason": reason, "via": via}
            if not data.get("latched"):
                data.update(latched=True, since_utc=event["utc"], by=by, reason=reason, via=via)
            data["history"] = (list(data.get("history", [])) + [event])[-HISTORY:]
            try:
                self._write(data)
            finally:
                self.flag.set()  # even on a full disk: the stop latches in this running service
            return self._public(data)

    def reset(self, by: str, note: str = "") -> dict[str, Any]:
        """Clear the latch (an operator's decision, recorded with who and when); :class:`NotLatchedError` if clear."""
        with self._lock:
            data = self._read()
            if not (self.flag.is_set() or data.get("latched")):
                raise NotLatchedError("the emergency stop is not latched; there is nothing to reset")
            event = {"event": "reset", "utc": _now(), "by": by, "reason": note, "via": "reset"}
            data.update(latched=False, last_reset={"utc": event["utc"], "by": by, "note": note})
            data["history"] = (list(data.get("history", [])) + [event])[-HISTORY:]
            self._write(data)
            self.flag.clear()
            return self._public(data)

    def state(self) -> dict[str, Any]:
        """Latched or not, since when, by whom, why; the last reset."""
        data = self._read()
        data["latched"] = self.latched
        return self._public(data)

    @staticmethod
    def _public(data: dict[str, Any]) -> dict[str, Any]:
        latched = bool(data.get("latched"))
        return {
            "latched": latched,
            "since_utc": data.get("since_utc") if latched else None,
            "by": data.get("by") if latched else None,
            "reason": data.get("reason") if latched else None,
            "last_reset": data.get("last_reset"),
        }

    def refusal(self, action: str) -> str | None:
        """Why ``action`` is refused now (None when not latched)."""
        if not self.latched:
            return None
        st = self.state()
        who = f" by {st['by']}" if st.get("by") else ""
        when = f" at {st['since_utc']}" if st.get("since_utc") else ""
        return (f"emergency stop latched{who}{when}: {action} refused until an operator resets it "
                "(POST /stop/reset or `orbitct reset`)")
