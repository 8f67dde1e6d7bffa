"""PWLS's data curvature ``A^T (w * A 1)``, kept on disk so that a run on the same views, geometry, grid and weights
reuses it instead of projecting every view forward and back once more.

The key is a digest of what the curvature depends on: the geometry of the views used, the grid, the projector and
the weights' source (the scan file's frame count, its dark and flat means and its first and last projections: a
scan's frames do not change once acquired). Files live in ``$ORBITCT_CACHE_DIR`` (default
``~/.cache/orbitct``)/``pwls-curvature``; the oldest go first when they exceed :data:`MAX_CACHE_BYTES`.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry, VolumeGrid
from orbitct.scanfile import ScanFile

MAX_CACHE_BYTES = 4 * 2**30
VERSION = b"pwls-curvature-1"


def cache_folder() -> Path:
    """Where curvatures are kept: ``$ORBITCT_CACHE_DIR/pwls-curvature`` (default ``~/.cache/orbitct``)."""
    base = os.environ.get("ORBITCT_CACHE_DIR") or Path.home() / ".cache" / "orbitct"
    return Path(base) / "pwls-curvature"


def curvature_key(scan: ScanFile, frames: NDArray[np.intp], geometry: ViewGeometry, grid: VolumeGrid) -> str:
    """The digest naming the data curvature of ``frames`` of ``scan`` (their weights) with ``geometry`` on ``grid``."""
    h = hashlib.sha256(VERSION)
    h.update(np.ascontiguousarray(geometry.vectors, dtype=np.float64).tobytes())
    h.update(repr((geometry.panel, grid.to_json())).encode())
    h.update(np.ascontiguousarray(frames, dtype=np.int64).tobytes())
    dark, flat = scan.dark_flat()
    h.update(np.ascontiguousarray(dark, dtype=np.float32).tobytes())
    h.update(np.ascontiguousarray(flat, dtype=np.float32).tobytes())
    h.update(str(scan.n_frames).encode())
    for i in (int(frames[0]), int(frames[-1])):
        h.update(np.ascontiguousarray(scan.frames[i]).tobytes())
    return h.hexdigest()[:32]


def load(key: str, shape: tuple[int, ...]) -> NDArray[np.float32] | None:
    """The cached curvature ``key`` of ``shape``, or None when there is none (or it cannot be read)."""
    path = cache_folder() / f"{key}.npy"
    try:
        array = np.load(path, mmap_mode=None, allow_pickle=False)
    except (OSError, ValueError):
        return None
    if array.shape != shape or array.dtype != np.float32:
        return None
    path.touch()  # recently used: kept longest
    return np.ascontiguousarray(array)


def save(key: str, curvature: NDArray[np.float32]) -> None:
    """Keep ``curvature`` under ``key`` (written whole or not at all), then trim the folder to its size bound; a cache
    that cannot be written is skipped."""
    folder = cache_folder()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        partial = folder / f"{key}.{os.getpid()}.partial"
        with open(partial, "wb") as f:
            np.save(f, np.ascontiguousarray(curvature, dtype=np.float32))
        partial.replace(folder / f"{key}.npy")
        _trim(folder)
    except OSError:
        return


def _trim(folder: Path) -> None:
    files = sorted(folder.glob("*.npy"), key=lambda p: p.stat().st_mtime, reverse=True)
    total = 0
    for path in files:
        total += path.stat().st_size
        if total > MAX_CACHE_BYTES:
            path.unlink(missing_ok=True)
