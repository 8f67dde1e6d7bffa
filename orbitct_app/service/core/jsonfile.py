"""The service's small JSON files (the stop latch, the tokens, plan states): each written whole or not at all."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path
from typing import Any


def write_json_atomically(path: Path, data: Any, *, private: bool = False, indent: int | None = 2) -> None:
    """Replace ``path`` with ``data`` as JSON so that a reader (another process, or the service after a crash or power
    loss) finds the old file or the new one, never a part: a temporary file beside it (named per process and
    thread), flushed to disk, then renamed over it. ``private``: readable by its owner only."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=indent)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
