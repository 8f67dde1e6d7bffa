"""A scan file that reads its frames' pixels from another: what ``orbitct calibrate --out`` writes.

Everything of the scan but ``/frames/data`` is copied (a few megabytes); ``/frames/data`` is an HDF5 virtual
dataset mapping the scan's, and ``/@frames_file`` names the scan by its path relative to this file, so the two
move together. The scan is neither copied nor changed. :class:`~orbitct.scanfile.ScanFile` accepts such a file
only while the scan it names is there and holds the frames it maps (HDF5 would read zeros in its place).
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py

#: the root attribute that names the scan file holding the frames' pixels (a path relative to this file)
FRAMES_FILE = "frames_file"


def frames_source(path: Path, f: h5py.File) -> Path:
    """The file that holds ``f``'s frame pixels: ``path`` itself, or the scan its ``/@frames_file`` names."""
    named = f.attrs.get(FRAMES_FILE)
    return path if named is None else (path.parent / str(named)).resolve()


def write_linked_scan(scan: str | os.PathLike[str], target: str | os.PathLike[str]) -> Path:
    """Write at ``target`` a scan file with everything of ``scan`` but its frames' pixels, which it reads from
    ``scan`` (or from the scan ``scan`` itself reads them from); ``target``."""
    src, out = Path(scan), Path(target)
    out.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(src, "r") as f:
        pixels = frames_source(src, f)
        relative = os.path.relpath(pixels, out.parent.resolve())
        data = f["frames/data"]
        part = out.with_name(f".{out.name}.part")
        try:
            with h5py.File(part, "w") as g:
                g.attrs.update(dict(f.attrs))
                g.attrs[FRAMES_FILE] = relative
                for name in f:
                    if name != "frames":
                        f.copy(f[name], g, name=name)
                frames = g.create_group("frames")
                frames.attrs.update(dict(f["frames"].attrs))
                for name in f["frames"]:
                    if name != "data":
                        f.copy(f["frames"][name], frames, name=name)
                layout = h5py.VirtualLayout(shape=data.shape, dtype=data.dtype)
                layout[...] = h5py.VirtualSource(relative, "frames/data", shape=data.shape)
                mapped = frames.create_virtual_dataset("data", layout, fillvalue=0)
                mapped.attrs.update(dict(data.attrs))
            part.replace(out)
        finally:
            part.unlink(missing_ok=True)
    return out


def linked_frames_problem(path: Path, f: h5py.File) -> str | None:
    """What is wrong with a file whose ``/@frames_file`` does not hold the frames its ``/frames/data`` maps, and
    what to do; None when nothing is (or the file holds its own frames)."""
    named = f.attrs.get(FRAMES_FILE)
    if named is None:
        return None
    if not isinstance(named, str) or not named:
        return f"/@{FRAMES_FILE} must name the scan file holding the frames, got {named!r}"
    data = f.get("frames/data")
    if not isinstance(data, h5py.Dataset) or not data.is_virtual:
        return f"/frames/data must map the frames of {named}, the file /@{FRAMES_FILE} names"
    if any(s.file_name != named or s.dset_name.lstrip("/") != "frames/data" for s in data.virtual_sources()):
        return f"/frames/data must map the frames of {named}, the file /@{FRAMES_FILE} names"
    scan = frames_source(path, f)
    fix = f"put the scan back at {scan}, or calibrate it again with --out"
    if not scan.is_file():
        return f"its frames are kept in {named}, which is not there; {fix}"
    try:
        with h5py.File(scan, "r") as s:
            held = s.get("frames/data")
            same = (
                isinstance(held, h5py.Dataset)
                and not held.is_virtual
                and held.shape == data.shape
                and held.dtype == data.dtype
            )
    except OSError:
        same = False
    return None if same else f"{named} no longer holds the frames this file reads from it; {fix}"
