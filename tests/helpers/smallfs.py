"""A size-limited filesystem that tests mount (tmpfs, as root) to fill a disk for real."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


@contextlib.contextmanager
def small_filesystem(path: Path, size_mb: int) -> Iterator[Path]:
    """Mount a ``size_mb`` tmpfs at ``path`` for the block; skips only where mounting is impossible (never in CI)."""
    path.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m,mode=0755", "tmpfs", str(path)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        why = f"cannot mount a {size_mb} MB tmpfs at {path}: {mounted.stderr.strip() or 'mount failed'}"
        if os.environ.get("CI"):
            pytest.fail(why + " (CI runs as root and must test a full disk)")
        pytest.skip(why)
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill(folder: Path, leave_bytes: int, name: str = "filler.bin") -> Path:
    """Write a file that leaves about ``leave_bytes`` free on ``folder``'s filesystem."""
    target = folder / name
    size = max(shutil.disk_usage(folder).free - leave_bytes, 0)
    with open(target, "wb") as fh:
        chunk = b"\0" * (1 << 20)
        while size > 0:
            n = fh.write(chunk[: min(size, len(chunk))])
            size -= n
        fh.flush()
        os.fsync(fh.fileno())
    return target
