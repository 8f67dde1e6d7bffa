"""The emergency-stop latch: set by any stop, cleared only by an operator's deliberate reset.

The latch is held in memory first: a byte of shared memory that every process of the service reads
(the web server, the guard, the rig process) and, beside it, a short shared note of who stopped,
why and when. Setting them cannot fail, so a stop latches before anything that can (files, the
database, logs). It is then recorded in ``<data_dir>/estop.json`` so that it survives a restart (a
bench stopped before a power cut is still stopped after it). A record that cannot be written (a
full disk, a read-only data directory) is retried in the background until it is written, and
reported meanwhile; it is never a reason not to halt or not to answer.
"""

from __future__ import annotations

import ctypes
import json
import logging
import multiprocessing as mp
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

from orbitct_app.service.core.jsonfile import write_json_atomically

log = logging.getLogger("orbitct.service.latch")
FILE_NAME = "estop.json"
HISTORY = 50  # stops and resets kept in the file
NOTE_BYTES = 2048  # the shared note: who stopped, why, when (JSON, truncated reasons)
RECORD_TRIES_S = (0.0, 0.02, 0.1)  # pauses before each try to record within a stop or reset
RETRY_S = 2.0  # then, in the background, until the record is written


class Flag(Protocol):
    """A flag shared between processes (:class:`SharedFlag`) or within one (``threading.Event``)."""

    def is_set(self) -> bool: ...

    def set(self) -> None: ...

    def clear(self) -> None: ...


class SharedFlag:
    """One byte of shared memory, without a lock: a process killed at any instant cannot leave it blocked; with a
    shared note of the latest stop (who, why, when) that the other processes read once the flag is set.

    (A ``multiprocessing.Event`` takes a lock even to read; a process killed while holding it would
    freeze every other process that reads the latch, the guard included.)
    """

    def __init__(self, context: Any = None) -> None:
        ctx = context or mp.get_context("spawn")
        self._value = ctx.RawValue(ctypes.c_ubyte, 0)
        self._seq = ctx.RawValue(ctypes.c_uint, 0)  # odd while the note is being written (a sequence lock)
        self._note = ctx.RawArray(ctypes.c_char, NOTE_BYTES)

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

    def write_note(self, note: dict[str, Any]) -> None:
        """Share ``note`` (small JSON) with every process that holds this flag."""
        data = json.dumps(note).encode()[: NOTE_BYTES - 1]
        self._seq.value += 1
        self._note.value = data
        self._seq.value += 1

    def read_note(self) -> dict[str, Any]:
        """The latest note ({} when none, or when it cannot be read whole after a few tries)."""
        for _ in range(20):
            before = self._seq.value
            if before % 2:
                time.sleep(0.0005)
                continue
            data = self._note.value
            if self._seq.value == before:
                try:
                    note = json.loads(data) if data else {}
                except ValueError:
                    return {}
                return note if isinstance(note, dict) else {}
        return {}


class NotLatchedError(Exception):
    """A reset asked for while no stop is latched."""


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def _apply(data: dict[str, Any], event: dict[str, Any]) -> None:
    """Apply one stop or reset event to the latch document (in time order: a stop older than the last reset is
    kept in the history but latches nothing)."""
    last_reset = (data.get("last_reset") or {}).get("utc") or ""
    if event["event"] == "stop":
        if not data.get("latched") and event["utc"] > last_reset:
            data.update(latched=True, since_utc=event["utc"], by=event["by"], reason=event["reason"], via=event["via"])
    elif event["utc"] >= (data.get("since_utc") or "") or not data.get("latched"):
        data.update(latched=False, last_reset={"utc": event["utc"], "by": event["by"], "note": event["reason"]})
    history = [e for e in data.get("history", []) if isinstance(e, dict)]
    if event not in history:
        history.append(event)
    data["history"] = sorted(history, key=lambda e: str(e.get("utc", "")))[-HISTORY:]


class StopLatch:
    """The latch of one bench: ``engage`` on any stop, ``reset`` by an operator; ``state`` for replies.

    ``engage`` is :meth:`latch` (memory, cannot fail) followed by :meth:`record` (the file, retried); a stop
    path that must halt before anything that can fail calls the two apart, with the halt between them."""

    def __init__(self, data_dir: Path, flag: Flag | None = None) -> None:
        self.path = Path(data_dir) / FILE_NAME
        self.flag: Flag = flag if flag is not None else threading.Event()
        self._lock = threading.Lock()
        self._pending: list[dict[str, Any]] = []  # events not yet in the file
        self._memory: dict[str, Any] = self._read()  # this process's view when the file cannot be read
        self.record_problem: str | None = None  # why the latest record could not be written (None: recorded)
        self._retrying = False
        if self._memory.get("latched"):
            self._share(self._memory)
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

    def _share(self, data: dict[str, Any]) -> None:
        write = getattr(self.flag, "write_note", None)
        if write is not None:
            write({k: (str(data.get(k) or "")[:500] or None) for k in ("since_utc", "by", "reason", "via")})

    # ------------------------------------------------------------ stop
    def latch(self, by: str, reason: str, via: str) -> dict[str, Any]:
        """Latch now, in memory, for every process of the service (cannot fail); the event to :meth:`record`."""
        event = {"event": "stop", "utc": _now(), "by": by, "reason": reason, "via": via}
        with self._lock:
            if not self.flag.is_set():
                self._share({"since_utc": event["utc"], "by": by, "reason": reason, "via": via})
                self.flag.set()
            _apply(self._memory, event)
            self._pending.append(event)
        return event

    def record(self) -> bool:
        """Write what is latched or reset to the file, a few times within a tenth of a second; if it still fails,
        keep trying in the background and say why in :attr:`record_problem` (never raises)."""
        for pause in RECORD_TRIES_S:
            time.sleep(pause)
            if self._write_pending():
                return True
        self._retry_in_background()
        return False

    def engage(self, by: str, reason: str, via: str) -> dict[str, Any]:
        """Latch (memory first, then the file); a second stop keeps the first one's time and author."""
        self.latch(by, reason, via)
        self.record()
        return self.state()

    def _write_pending(self) -> bool:
        with self._lock:
            if not self._pending:
                self.record_problem = None
                return True
            on_disk = self._read()
            data = on_disk if on_disk or not self.path.exists() else dict(self._memory)
            for event in self._pending:
                _apply(data, event)
            try:
                write_json_atomically(self.path, data)
            except OSError as exc:
                self.record_problem = f"the latch could not be recorded in {self.path} ({exc.strerror or exc})"
                return False
            self._pending.clear()
            self._memory = data
            if self.record_problem is not None:
                log.warning("the latch is recorded in %s again", self.path)
            self.record_problem = None
            return True

    def _retry_in_background(self) -> None:
        with self._lock:
            if self._retrying:
                return
            self._retrying = True
        log.error("%s; retrying every %g s (the stop holds in memory)", self.record_problem, RETRY_S)

        def retry() -> None:
            while not self._write_pending():
                time.sleep(RETRY_S)
            with self._lock:
                self._retrying = False

        threading.Thread(target=retry, name="orbitct-latch-record", daemon=True).start()

    # ------------------------------------------------------------ reset
    def reset(self, by: str, note: str = "") -> dict[str, Any]:
        """Clear the latch (an operator's decision, recorded with who and when); :class:`NotLatchedError` if clear.
        A reset that cannot be written yet is kept in memory and retried: until it is, a restart latches again."""
        event = {"event": "reset", "utc": _now(), "by": by, "reason": note, "via": "reset"}
        with self._lock:
            if not (self.flag.is_set() or self._read().get("latched")):
                raise NotLatchedError("the emergency stop is not latched")
            _apply(self._memory, event)
            self._pending.append(event)
            self.flag.clear()
        self.record()
        return self.state()

    # ------------------------------------------------------------ state
    def state(self) -> dict[str, Any]:
        """Latched or not, since when, by whom, why; the last reset; whether it is recorded on disk."""
        with self._lock:
            on_disk = self._read()
            data = on_disk if not self._pending else dict(self._memory)
            problem = self.record_problem
        latched = self.latched
        if latched and not data.get("latched"):  # latched by another process that could not write the file yet
            note: dict[str, Any] = getattr(self.flag, "read_note", dict)()
            data = {**data, **{k: v for k, v in note.items() if v}}
        data["latched"] = latched
        if problem is None and bool(on_disk.get("latched")) != latched:
            problem = (
                f"{self.path} does not record the {'stop' if latched else 'reset'} yet (the process that took "
                "it keeps trying)"
            )
        return {**self._public(data), "recorded": problem is None, "record_problem": problem}

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
        return f"emergency stop latched{who}{when}: {action} refused until an operator resets it"
