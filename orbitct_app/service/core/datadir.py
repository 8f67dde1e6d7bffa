"""One service per data directory: an exclusive lock on ``<data_dir>/service.lock`` for the service's lifetime.

The lock is the kernel's (``flock``), so it goes with the process however that ends; the file says who holds it.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

LOCK_NAME = "service.lock"


class DataDirBusy(RuntimeError):
    """Another service holds the data directory; the message says which (pid, host, port, since when)."""


class DataDirLock:
    """Held while a service runs on ``data_dir``; :meth:`acquire` refuses when another one holds it."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = Path(data_dir)
        self.path = self.data_dir / LOCK_NAME
        self._fd: int | None = None

    def holder(self) -> dict[str, Any]:
        """What the lock file says about the service holding it (``{}`` if unreadable)."""
        try:
            data = json.loads(self.path.read_text(encoding="utf-8") or "{}")
        except (OSError, ValueError):
            return {}
        return data if isinstance(data, dict) else {}

    def acquire(self, **about: Any) -> None:
        """Take the lock (idempotent) and write pid, host, start time and ``about`` (e.g. the port) into it."""
        if self._fd is not None:
            return
        self.data_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            who = self.holder()
            desc = ", ".join(f"{k} {who[k]}" for k in ("pid", "host", "port", "started_utc") if k in who)
            raise DataDirBusy(
                f"another orbitct service ({desc or 'details unknown'}) uses the data directory "
                f"{self.data_dir}; stop it first, or start this one with another --data-dir"
            ) from None
        self._fd = fd
        body = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            **about,
        }
        with contextlib.suppress(OSError):  # a full disk keeps the lock, only not its description
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(body).encode(), 0)

    def release(self) -> None:
        """Let go of the lock."""
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, 0)
            os.close(self._fd)  # closing drops the flock
            self._fd = None
