"""Streaming writer for scan files (``scan-file.md``, version 1).

Frames are appended one at a time and the file is flushed after each, so a
process that dies leaves a readable file holding every frame already appended.
"""

from __future__ import annotations

import json
import os
import socket
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike

from orbitct import __version__
from orbitct.diskspace import format_bytes, free_bytes
from orbitct.geometry import Panel, ViewGeometry
from orbitct.scanfile.errors import DiskFullError, ScanFileError
from orbitct.scanfile.keys import ImageKey

FORMAT = "orbitct.scan"
VERSION = 1
STATUSES = ("acquiring", "complete", "aborted")
_GEOM_CHUNK = 256


def to_json(obj: Any) -> str:
    """JSON text of an attribute value (sorted keys; arrays as lists)."""
    return json.dumps(obj, sort_keys=True, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))


def _axis_units(names: Mapping[str, str] | None) -> dict[str, str]:
    out: dict[str, str] = {}
    for name, unit in (names or {}).items():
        if "." not in name or "/" in name:
            raise ScanFileError(f"axis name {name!r} must look like 'device.axis' (no '/')")
        out[name] = unit
    return out


def _put_row(ds: h5py.Dataset, i: int, value: Any) -> None:
    """Grow ``ds`` to ``i + 1`` rows and write row ``i`` (low-level h5py: ~10x less overhead per call)."""
    tail = ds.shape[1:]
    ds.id.set_extent((i + 1,) + tail)
    row = np.ascontiguousarray(np.asarray(value, dtype=ds.dtype).reshape((1,) + tail))
    space = ds.id.get_space()
    space.select_hyperslab((i,) + (0,) * len(tail), row.shape)
    ds.id.write(h5py.h5s.create_simple(row.shape), space, row)


class ScanWriter:
    """Append frames to a new scan file; use as a context manager."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        panel: Panel,
        *,
        frame_dtype: str = "uint16",
        axes: Mapping[str, str] | None = None,
        orbit_name: str = "",
        orbit_params: Mapping[str, Any] | None = None,
        config: Mapping[str, Any] | None = None,
        marker_diameter_mm: float | None = None,
        compression: str | None = None,
        true_geometry: bool = False,
        overwrite: bool = False,
        min_free_bytes: int | None = None,
    ) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise ScanFileError(f"{self.path}: already exists (pass overwrite to replace it)")
        if np.dtype(frame_dtype) not in (np.dtype("uint16"), np.dtype("float32")):
            raise ScanFileError(f"frame dtype must be uint16 or float32, got {frame_dtype}")
        self.panel = panel
        self._axes = _axis_units(axes)
        self._n = 0
        self._closed = False
        self._broken = False
        frame_bytes = panel.rows * panel.cols * np.dtype(frame_dtype).itemsize
        # HDF5 cannot recover from a write that fails for want of space (h5py#914: the file handle is left
        # half-closed and the process may crash on exit), so a frame is refused while there is still room
        # to close the file cleanly: two frames and 1 MiB for the metadata, unless told otherwise
        self._min_free = 2 * frame_bytes + (1 << 20) if min_free_bytes is None else int(min_free_bytes)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = h5py.File(self.path, "w")
        self._f = f
        f.attrs.update({"format": FORMAT, "version": VERSION, "status": "acquiring", "status_reason": ""})
        g = f.create_group("detector")
        g.attrs.update({"rows": panel.rows, "cols": panel.cols, "pitch_mm": np.array(panel.pitch_mm)})
        fr = f.create_group("frames")
        r, c = panel.shape
        fr.create_dataset(
            "data",
            shape=(0, r, c),
            maxshape=(None, r, c),
            dtype=frame_dtype,
            chunks=(1, r, c),
            compression=compression,
        )
        fr.create_dataset("image_key", shape=(0,), maxshape=(None,), dtype="i1", chunks=(_GEOM_CHUNK,))
        fr.create_dataset("time_s", shape=(0,), maxshape=(None,), dtype="f8", chunks=(_GEOM_CHUNK,))
        for grp in ("encoders", "commanded"):
            eg = fr.create_group(grp)
            for name, unit in self._axes.items():
                ds = eg.create_dataset(name, shape=(0,), maxshape=(None,), dtype="f8", chunks=(_GEOM_CHUNK,))
                ds.attrs["unit"] = unit
        nom = f.create_group("geometry/nominal")
        nom.create_dataset("vectors", shape=(0, 12), maxshape=(None, 12), dtype="f8", chunks=(_GEOM_CHUNK, 12))
        nom.create_dataset("matrices", shape=(0, 3, 4), maxshape=(None, 3, 4), dtype="f8", chunks=(_GEOM_CHUNK, 3, 4))
        if true_geometry:  # simulated acquisitions: the view each frame was rendered at, written with the frame
            f.create_dataset(
                "truth/geometry/vectors", shape=(0, 12), maxshape=(None, 12), dtype="f8", chunks=(_GEOM_CHUNK, 12)
            )
        # handles of every per-frame dataset, looked up once (append runs once per frame)
        self._per_frame = {
            name: f[name]
            for name in [
                "frames/data",
                "frames/image_key",
                "frames/time_s",
                "geometry/nominal/vectors",
                "geometry/nominal/matrices",
            ]
            + (["truth/geometry/vectors"] if true_geometry else [])
            + [f"frames/{grp}/{axis}" for grp in ("encoders", "commanded") for axis in self._axes]
        }
        mk = f.create_group("markers")
        if marker_diameter_mm is not None:
            mk.attrs["diameter_mm"] = float(marker_diameter_mm)
        og = f.create_group("orbit")
        og.attrs.update({"name": orbit_name, "params_json": to_json(dict(orbit_params or {}))})
        pg = f.create_group("provenance")
        pg.attrs.update(
            {
                "software_version": __version__,
                "config_json": to_json(dict(config or {})),
                "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                # who is writing: lets a repair tell a live acquisition from one that was killed
                "writer_pid": os.getpid(),
                "writer_host": socket.gethostname(),
            }
        )
        f.flush()

    @property
    def n_frames(self) -> int:
        """Frames appended so far."""
        return self._n

    def append(
        self,
        frame: ArrayLike,
        image_key: ImageKey | int | str,
        time_s: float,
        *,
        nominal_vector: ArrayLike | None = None,
        encoders: Mapping[str, float] | None = None,
        commanded: Mapping[str, float] | None = None,
        true_vector: ArrayLike | None = None,
        flush: bool = True,
    ) -> int:
        """Append one frame with its metadata and flush; returns the frame index."""
        if self._closed:
            raise ScanFileError(f"{self.path}: writer is closed")
        if self._broken:
            raise ScanFileError(f"{self.path}: a frame could not be written; this writer takes no more")
        try:
            key = ImageKey.parse(image_key)
        except ValueError as exc:
            raise ScanFileError(str(exc)) from None
        arr = np.asarray(frame)
        if arr.shape != self.panel.shape:
            raise ScanFileError(f"frame shape {arr.shape} does not match detector {self.panel.shape}")
        vec = np.full(12, np.nan) if nominal_vector is None else np.asarray(nominal_vector, float).reshape(12)
        if key == ImageKey.PROJECTION and not np.isfinite(vec).all():
            raise ScanFileError("a projection frame needs a finite nominal geometry vector")
        axis_values = {"encoders": encoders or {}, "commanded": commanded or {}}
        for grp, values in axis_values.items():
            unknown = set(values) - set(self._axes)
            if unknown:
                raise ScanFileError(f"{grp}: unknown axes {sorted(unknown)}; declared axes are {sorted(self._axes)}")
        i, ds = self._n, self._per_frame
        if self._min_free > 0:
            free = free_bytes(self.path.parent)
            if free < self._min_free:
                raise DiskFullError(
                    f"{self.path}: frame {i} not written: {format_bytes(free)} free, "
                    f"{format_bytes(self._min_free)} needed to write it and close the file cleanly; "
                    f"the {i} frames before it are kept"
                )
        if ds["frames/data"].dtype == np.uint16:
            arr = np.clip(np.rint(arr), 0, 65535).astype(np.uint16) if arr.dtype != np.uint16 else arr
        try:
            _put_row(ds["frames/data"], i, arr)
            for grp, values in axis_values.items():
                for name in self._axes:
                    _put_row(ds[f"frames/{grp}/{name}"], i, values.get(name, np.nan))
            _put_row(ds["geometry/nominal/vectors"], i, vec)
            _put_row(ds["geometry/nominal/matrices"], i, ViewGeometry(vec, self.panel).matrices[0])
            if "truth/geometry/vectors" in ds:
                truth = np.full(12, np.nan) if true_vector is None else np.asarray(true_vector, float).reshape(12)
                _put_row(ds["truth/geometry/vectors"], i, truth)
            _put_row(ds["frames/time_s"], i, float(time_s))
            # image_key is written last: its length is the count of complete frames.
            _put_row(ds["frames/image_key"], i, int(key))
            if flush:
                self._f.flush()
        except (OSError, RuntimeError) as exc:  # HDF5 reports a failed write (a full disk) as either
            self._failed_write(i, exc)
        self._n = i + 1
        return i

    def _failed_write(self, i: int, exc: BaseException) -> None:
        """Frame ``i`` could not be written: leave it uncounted, stop writing, and say why in one line."""
        for ds in self._per_frame.values():  # every per-frame dataset back to i rows, so that they agree
            try:
                if ds.shape[0] > i:
                    ds.id.set_extent((i,) + ds.shape[1:])
            except (OSError, RuntimeError):
                pass  # readers also leave out a last frame whose pixels are not in the file
        self._broken = True
        self._detach()
        text = str(exc)
        full = "errno = 28" in text or "No space left" in text
        causes = {
            "errno = 30": "the filesystem turned read-only",
            "errno = 5,": "the disk reported an I/O error",
            "errno = 122": "the disk quota is used up",
        }
        why = (
            "the disk is full"
            if full
            else next((c for k, c in causes.items() if k in text), text.splitlines()[0][:200])
        )
        raise (DiskFullError if full else ScanFileError)(
            f"{self.path}: frame {i} could not be written ({why}); the {i} frames before it are kept"
        ) from None

    def _detach(self) -> None:
        """After a write the disk refused (full, read-only, an I/O error), point HDF5's file descriptor at the null
        device: HDF5 cannot recover from such a write, and closing the file would make it write again and crash the
        process (h5py#914). What was flushed before stays on disk; `orbitct scan repair` marks the file aborted."""
        try:
            fd = int(self._f.id.get_vfd_handle())
        except (AttributeError, OSError, RuntimeError, TypeError, ValueError):
            return  # not the POSIX driver: nothing to detach
        null = os.open(os.devnull, os.O_RDWR)
        try:
            os.dup2(null, fd)
        finally:
            os.close(null)

    def write_truth(
        self,
        vectors: ArrayLike | None = None,
        markers_xyz: ArrayLike | None = None,
        phantom: Mapping[str, Any] | None = None,
    ) -> None:
        """Store the simulation truth: geometry of every frame (unless written frame by frame), marker centres, phantom."""
        g = self._f.require_group("truth")
        if vectors is not None:
            if "geometry/vectors" in g:
                del g["geometry/vectors"]
            g.create_dataset("geometry/vectors", data=np.asarray(vectors, dtype=float).reshape(-1, 12))
        if markers_xyz is not None:
            if "markers/xyz" in g:
                del g["markers/xyz"]
            g.create_dataset("markers/xyz", data=np.asarray(markers_xyz, dtype=float).reshape(-1, 3))
        if phantom is not None:
            g.attrs["phantom_json"] = to_json(dict(phantom))
        self._f.flush()

    def write_dataset(self, path: str, data: ArrayLike, **attrs: Any) -> None:
        """Store an extra dataset at ``path`` (replacing one there) with attributes, and flush."""
        if path in self._f:
            del self._f[path]
        ds = self._f.create_dataset(path, data=np.asarray(data))
        for k, v in attrs.items():
            ds.attrs[k] = to_json(v) if isinstance(v, (dict, list)) else v
        self._f.flush()

    def set_attrs(self, group: str, **attrs: Any) -> None:
        """Set extra attributes on a group (created if missing)."""
        g = self._f.require_group(group)
        for k, v in attrs.items():
            g.attrs[k] = to_json(v) if isinstance(v, (dict, list)) else v
        self._f.flush()

    def finish(self, status: str = "complete", reason: str = "") -> None:
        """Set the final status and close the file."""
        if self._closed:
            return
        if status not in STATUSES:
            raise ScanFileError(f"status must be one of {STATUSES}, got {status!r}")
        self._closed = True
        try:
            self._f.attrs["status"] = status
            self._f.attrs["status_reason"] = reason
            self._f.close()
        except (OSError, RuntimeError):
            if not self._broken:
                raise
            # the disk is full: the status stays 'acquiring' and `orbitct scan repair` marks it aborted later
            self._per_frame.clear()
            try:
                self._f.close()
            except (OSError, RuntimeError):
                pass

    def __enter__(self) -> ScanWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: Any) -> None:
        if exc is None:
            self.finish("complete")
        else:
            said = str(exc) or ("interrupted (Ctrl-C)" if isinstance(exc, KeyboardInterrupt) else "stopped by an error")
            self.finish("aborted", said)
