"""File access confined to the service's data directory (no path traversal, no links out)."""

from __future__ import annotations

import re
from pathlib import Path

from orbitct_app.service.core.errors import NotFound

_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def confined(base: Path, *parts: str) -> Path:
    """``base/parts...`` if every part is a plain name and the real path stays inside ``base``; 404 otherwise."""
    root = base.resolve()
    for part in parts:
        if not _SAFE_NAME.match(part) or part in (".", ".."):
            raise NotFound(f"no file named {part[:60]!r}")
    path = root.joinpath(*parts).resolve()
    if root != path and root not in path.parents:
        raise NotFound("no such file")
    if not path.is_file():
        raise NotFound(f"no file named {'/'.join(parts)[:120]!r}")
    return path
