"""The service's child processes (rig, guard, simulated bench): how soon one is restarted, how one is ended."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
from typing import Any

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> None:
    """In a child process: be killed (SIGKILL) when the parent dies, however it dies (Linux; elsewhere nothing).

    A worker must not outlive the service: it would write into scan files whose records say it never did.
    """
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(1)


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
