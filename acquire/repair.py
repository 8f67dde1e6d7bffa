"""Repair a scan file left behind by a killed acquisition: keep every complete frame, mark it aborted."""

from __future__ import annotations

import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path

import h5py

from acquire.errors import RepairError
from orbitct.scanfile import ScanFile, ScanFileError
from orbitct.scanfile.reader import frames_with_pixels
from orbitct.scanfile.writer import FORMAT

INTERRUPTED = "interrupted"


@dataclass(frozen=True)
class RepairReport:
    """What :func:`repair_scan` found and did."""

    path: Path
    status_before: str
    n_frames: int
    truncated_from: int | None
    changed: bool

    def summary(self) -> str:
        """One line for people."""
        if not self.changed:
            return (
                f"{self.path}: status is already {self.status_before!r} with {self.n_frames} frames; nothing to repair"
            )
        cut = f" (partial frame data cut from {self.truncated_from})" if self.truncated_from is not None else ""
        if self.status_before != "acquiring":
            return f"{self.path}: {self.status_before}; kept {self.n_frames} complete frames{cut}"
        return f"{self.path}: was {self.status_before!r}; kept {self.n_frames} complete frames{cut}; marked aborted ({INTERRUPTED})"


def _per_frame_datasets(f: h5py.File) -> list[h5py.Dataset]:
    out: list[h5py.Dataset] = []
    for name in (
        "frames/data",
        "frames/time_s",
        "geometry/nominal/vectors",
        "geometry/nominal/matrices",
        "truth/geometry/vectors",
    ):
        if name in f:
            out.append(f[name])
    for grp in ("frames/encoders", "frames/commanded"):
        if grp in f:
            out.extend(ds for ds in f[grp].values() if isinstance(ds, h5py.Dataset))
    return out


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process
    return True


def live_writer(f: h5py.File, mtime: float, quiet_s: float) -> str | None:
    """Why an ``acquiring`` file may still be written by its acquisition, or None when its writer is gone.

    On this machine the writer's process id decides; a file written elsewhere (a network file system) or
    without one counts as live while it changed in the last ``quiet_s`` seconds (``mtime``: taken before
    opening, which itself touches the file).
    """
    prov = f["provenance"].attrs if "provenance" in f else {}
    pid, host = prov.get("writer_pid"), prov.get("writer_host")
    if pid is not None and host == socket.gethostname():
        if int(pid) != os.getpid() and _pid_alive(int(pid)):
            return f"process {int(pid)} on this machine is still writing it (a running acquisition)"
        return None
    age = time.time() - mtime
    if age < quiet_s:
        where = f" (written on {host})" if host else ""
        return f"it changed {age:.0f} s ago{where}: an acquisition may still be writing it"
    return None


def repair_scan(path: str | os.PathLike[str], *, force: bool = False, quiet_s: float = 30.0) -> RepairReport:
    """Mark a scan still ``acquiring`` as ``aborted`` with reason ``interrupted``, trimming partial frames.

    A file whose acquisition may still be running (:func:`live_writer`) is refused unless ``force``:
    trimming it would cut frames out from under the writer (HDF5 file locking is often off on network file
    systems, so the lock alone does not protect it).
    """
    p = Path(path)
    if not p.is_file():
        raise RepairError(f"{p}: no such file")
    mtime = p.stat().st_mtime
    try:
        f = h5py.File(p, "r+")
    except OSError as exc:
        raise RepairError(
            f"{p}: cannot open as HDF5 for writing ({exc}); is another process still writing it?"
        ) from None
    try:
        if f.attrs.get("format") != FORMAT:
            raise RepairError(f"{p}: not an orbitct scan file (format tag {f.attrs.get('format')!r})")
        status = str(f.attrs.get("status", "complete"))
        if "frames/image_key" not in f:
            raise RepairError(f"{p}: has no /frames/image_key; nothing can be recovered")
        # image_key is written last for each frame: its length counts the complete frames, unless the disk
        # filled up while the last ones were written and their pixels never reached the file
        n = int(f["frames/image_key"].shape[0])
        if "frames/data" in f and isinstance(f["frames/data"], h5py.Dataset):
            n = min(n, frames_with_pixels(f["frames/data"], n, p.stat().st_size))
        if status != "acquiring" and n == f["frames/image_key"].shape[0]:
            return RepairReport(p, status, n, None, False)
        busy = None if force or status != "acquiring" else live_writer(f, mtime, quiet_s)
        if busy is not None:
            raise RepairError(f"{p}: not repaired: {busy}; stop that acquisition first (or repair anyway with --force)")
        longest = max([n] + [ds.shape[0] for ds in _per_frame_datasets(f)])
        n = min([n] + [ds.shape[0] for ds in _per_frame_datasets(f)])
        if f["frames/image_key"].shape[0] > n:
            f["frames/image_key"].resize(n, axis=0)
        for ds in _per_frame_datasets(f):
            if ds.shape[0] > n:
                ds.resize(n, axis=0)
        if "truth/geometry/vectors" in f and f["truth/geometry/vectors"].shape[0] != n:
            del f["truth/geometry/vectors"]  # partial truth is not the truth of this file
        if status == "acquiring":
            f.attrs["status"] = "aborted"
            f.attrs["status_reason"] = INTERRUPTED
        f.flush()
    finally:
        f.close()
    try:
        with ScanFile(p) as sf:
            n_ok = sf.n_frames
    except ScanFileError as exc:
        raise RepairError(f"{p}: repaired but still not valid: {exc}") from None
    return RepairReport(p, status, n_ok, longest if longest != n_ok else None, True)
