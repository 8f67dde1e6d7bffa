"""Files of the data directory: access confined to it (no path traversal, no links out), and scan summaries."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from orbitct_app.service.core.errors import NotFound
from orbitct_app.service.core.failures import failure_sentence

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


def summarize_scan(path: Path) -> dict[str, Any]:
    """:func:`orbitct.scanfile.scan_summary` of the file at ``path``, or ``{"error": ...}`` when it cannot be read."""
    from orbitct.scanfile import ScanFile, ScanFileError
    from orbitct.scanfile import scan_summary as summarize

    try:
        with ScanFile(path) as sf:
            return summarize(sf)
    except ScanFileError as exc:
        return {"error": f"scan file unreadable: {exc}".replace(str(path), path.name)}
    except Exception as exc:  # noqa: BLE001 - a damaged file must not cost the scan's record
        return {"error": f"scan file unreadable: {failure_sentence(exc)}".replace(str(path), path.name)}
