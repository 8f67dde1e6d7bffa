"""Free space on a filesystem and sizes for people: the one home of both (writer, acquisition, service)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

MB = 1024 * 1024


def format_bytes(n: float) -> str:
    """Human-readable size: ``512 kB``, ``37.1 MB``, ``2.40 GB``."""
    if n < MB:
        return f"{n / 1024:.0f} kB"
    if n < 1024 * MB:
        return f"{n / MB:.1f} MB"
    return f"{n / (1024 * MB):.2f} GB"


def free_bytes(path: str | os.PathLike[str]) -> int:
    """Free bytes, for this user, on the filesystem that holds ``path`` (its nearest existing folder)."""
    folder = Path(path).resolve()
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return shutil.disk_usage(folder).free


__all__ = ["MB", "format_bytes", "free_bytes"]
