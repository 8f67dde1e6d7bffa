"""Run the acquisition ahead of other work on the machine, where the operating system allows it.

A continuous scan exposes each frame at an angle of a sweep that does not wait: a process that is starved of CPU
(a reconstruction, a browser, another user's job) exposes late. The service's bench process asks for this priority
itself; ``orbitct scan`` asks for it around the scan. Raising priority needs root or CAP_SYS_NICE; without them the
scan runs at normal priority and says so in the log.

A process can also pause itself: Python's full garbage collection walks every object the process holds, which in a
long-lived process (the service, a test session) takes 50-100 ms or more, and comes at a moment nobody chooses.
:func:`steady_collection` keeps the objects alive when a scan starts out of every collection until it ends.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

log = logging.getLogger(__name__)

#: nice value asked for the acquisition (the same as the service's bench process)
BENCH_NICE = -5
#: nice value of batch work beside a bench (the service's calibration, reconstruction and planning jobs)
JOB_NICE = 5


def _threads() -> list[int]:
    """This process's threads (Linux sets priority per thread), or the calling one elsewhere."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError):
            return [int(p.name) for p in Path("/proc/self/task").iterdir() if p.name.isdigit()]
    return [0]


def _set(tid: int, nice: int) -> bool:
    try:
        os.setpriority(os.PRIO_PROCESS, tid, nice)
    except (OSError, ProcessLookupError):
        return False
    return True


@contextlib.contextmanager
def bench_priority(nice_value: int = BENCH_NICE) -> Iterator[bool]:
    """Run the block with every thread of this process at ``nice_value`` where permitted (yields whether it was).

    Threads started inside the block inherit it. Afterwards each thread returns to the priority it had, and those
    started inside to the caller's.
    """
    before = {tid: os.getpriority(os.PRIO_PROCESS, tid) for tid in _threads()}
    own = os.getpriority(os.PRIO_PROCESS, 0)
    changed = [tid for tid, nice in before.items() if nice > nice_value and _set(tid, nice_value)]
    raised = os.getpriority(os.PRIO_PROCESS, 0) <= nice_value
    if not raised:
        log.info("acquisition priority stays normal (raising it needs root or CAP_SYS_NICE)")
    try:
        yield raised
    finally:
        if changed:
            for tid in _threads():
                _set(tid, before.get(tid, own))


_steady_depth = 0
_steady_lock = threading.Lock()


@contextlib.contextmanager
def steady_collection() -> Iterator[None]:
    """Run the block with the objects alive at its start frozen out of garbage collection (``gc.freeze``).

    Collections inside the block then walk only what the block created, which stays small, instead of every
    object of the process: on this project's 2-core machine a full collection paused a scan for up to 96 ms, five
    degrees of a sweep at 8 frames/s. Afterwards the frozen objects are collected as before. Nested blocks freeze once.
    """
    global _steady_depth
    with _steady_lock:  # scans in several threads of one process: frozen from the first start to the last end
        if _steady_depth == 0:
            gc.freeze()
        _steady_depth += 1
    try:
        yield
    finally:
        with _steady_lock:
            _steady_depth -= 1
            if _steady_depth == 0:
                gc.unfreeze()
