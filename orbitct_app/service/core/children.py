"""The service's child processes (rig, guard, simulated bench): how soon one is restarted, how one is ended."""

from __future__ import annotations

import contextlib
from typing import Any


class Backoff:
    """Delays between restarts: ``first_s`` doubling up to ``max_s``; back to ``first_s`` after ``stable_s`` of uptime."""

    def __init__(self, first_s: float = 0.5, max_s: float = 30.0, stable_s: float = 60.0) -> None:
        self.first_s, self.max_s, self.stable_s = first_s, max_s, stable_s
        self._next = first_s
        self.restarts = 0

    def delay(self, uptime_s: float) -> float:
        """The wait before the next start of a process that ran ``uptime_s`` seconds."""
        if uptime_s >= self.stable_s:
            self._next = self.first_s
        delay = self._next
        self._next = min(self._next * 2.0, self.max_s)
        self.restarts += 1
        return delay


def end_child(process: Any, conn: Any, wait_s: float) -> None:
    """Ask a child process to end (``"shutdown"`` down its pipe), wait ``wait_s``, then kill it; close the pipe."""
    if conn is not None:
        with contextlib.suppress(OSError, ValueError):
            conn.send("shutdown")
    if process is not None:
        process.join(wait_s)
        if process.is_alive():
            process.kill()
            process.join(5.0)
    if conn is not None:
        conn.close()
