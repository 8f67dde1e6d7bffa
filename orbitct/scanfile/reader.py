"""Validating reader for scan files (``docs/scan-file.md``)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import GeometryError, Panel, ViewGeometry
from orbitct.scanfile.errors import ScanFileError
from orbitct.scanfile.keys import ImageKey
from orbitct.scanfile.results import ScanResults
from orbitct.scanfile.writer import FORMAT, STATUSES, VERSION

GEOMETRY_NAMES = ("nominal", "calibrated", "truth")


class ScanFile(ScanResults):
    """An open scan file, checked against ``scan-file.md`` on open. Use as a context manager."""

    def __init__(self, path: str | os.PathLike[str], mode: str = "r") -> None:
        self.path = Path(path)
        if mode not in ("r", "r+"):
            raise ScanFileError(f"{self.path}: mode must be 'r' or 'r+', got {mode!r}")
        if not self.path.is_file():
            raise ScanFileError(f"{self.path}: no such file")
        try:
            self._f = h5py.File(self.path, mode)
        except OSError as exc:
            raise ScanFileError(f"{self.path}: not a readable HDF5 file ({exc})") from None
        try:
            self._validate()
        except ScanFileError:
            self._f.close()
            raise

    # ------------------------------------------------------------ validation
    def _validate(self) -> None:
        f = self._f
        fmt = f.attrs.get("format")
        if fmt != FORMAT:
            raise self._fail(f"format tag is {fmt!r}, expected {FORMAT!r}")
        ver = f.attrs.get("version")
        try:
            ok_version = ver is not None and int(ver) == VERSION
        except (TypeError, ValueError):
            ok_version = False
        if not ok_version:
            shown = ver.item() if isinstance(ver, np.generic) else ver
            raise self._fail(f"version is {shown!r}, this reader supports version {VERSION}")
        status = f.attrs.get("status", "complete")
        if status not in STATUSES:
            raise self._fail(f"status is {status!r}, expected one of {STATUSES}")
        if "detector" not in f:
            raise self._fail("missing group /detector")
        da = f["detector"].attrs
        for key in ("rows", "cols", "pitch_mm"):
            if key not in da:
                raise self._fail(f"missing attribute /detector@{key}")
        pitch = np.asarray(da["pitch_mm"], dtype=float).ravel()
        if pitch.shape != (2,):
            raise self._fail(f"/detector@pitch_mm must hold 2 numbers [col, row], got {pitch.tolist()}")
        try:
            self.panel = Panel(int(da["rows"]), int(da["cols"]), float(pitch[0]), float(pitch[1]))
        except GeometryError as exc:
            raise self._fail(f"/detector attributes: {exc}") from None
        for ds in ("frames/data", "frames/image_key"):
            if ds not in f:
                raise self._fail(f"missing dataset /{ds}")
        data, key = f["frames/data"], f["frames/image_key"]
        if data.ndim != 3 or data.shape[1:] != self.panel.shape:
            raise self._fail(
                f"/frames/data has shape {data.shape}, expected (N, {self.panel.rows}, {self.panel.cols})"
            )
        if data.dtype not in (np.uint16, np.float32):
            raise self._fail(f"/frames/data has dtype {data.dtype}, expected uint16 or float32")
        lengths = {"/frames/data": data.shape[0], "/frames/image_key": key.shape[0]}
        if "frames/time_s" in f:
            lengths["/frames/time_s"] = f["frames/time_s"].shape[0]
        if status == "acquiring":
            n = min(lengths.values())  # a scan still being written, or one that crashed
        else:
            if len(set(lengths.values())) != 1:
                raise self._fail(f"per-frame datasets disagree in length: {lengths}")
            n = data.shape[0]
        self.n_frames = int(n)
        keys = key[: self.n_frames]
        bad = set(np.unique(keys).tolist()) - {int(k) for k in ImageKey}
        if bad:
            raise self._fail(f"/frames/image_key holds {sorted(bad)}, allowed are {', '.join(str(k.value) for k in ImageKey)} "
                             f"({', '.join(k.label for k in ImageKey)})")
        self.image_key: NDArray[np.int8] = np.asarray(keys, dtype=np.int8)
        for name in ("nominal", "calibrated"):
            if f"geometry/{name}" in f:
                self._check_geometry(f"geometry/{name}")
        if "truth/geometry" in f:
            self._check_geometry("truth/geometry")

    def _check_geometry(self, group: str) -> None:
        g = self._f[group]
        if "vectors" not in g:
            raise self._fail(f"missing dataset /{group}/vectors")
        vec = g["vectors"]
        if vec.ndim != 2 or vec.shape[1] != 12 or vec.shape[0] < self.n_frames:
            raise self._fail(f"/{group}/vectors has shape {vec.shape}, expected ({self.n_frames}, 12)")
        if "matrices" in g and (g["matrices"].shape[1:] != (3, 4) or g["matrices"].shape[0] < self.n_frames):
            raise self._fail(f"/{group}/matrices has shape {g['matrices'].shape}, expected ({self.n_frames}, 3, 4)")
        if group == "geometry/calibrated":
            return  # calibration may leave NaN for views it could not solve
        v = np.asarray(vec[: self.n_frames])
        bad = np.flatnonzero((self.image_key == ImageKey.PROJECTION) & ~np.isfinite(v).all(axis=1))
        if bad.size:
            raise self._fail(
                f"/{group}/vectors is not finite on projection frames {bad[:5].tolist()}"
                + (" ..." if bad.size > 5 else "")
            )

    # ------------------------------------------------------------- metadata
    @property
    def status(self) -> str:
        """``acquiring``, ``complete`` or ``aborted``."""
        return str(self._f.attrs.get("status", "complete"))

    @property
    def status_reason(self) -> str:
        """Why the scan was aborted (empty otherwise)."""
        return str(self._f.attrs.get("status_reason", ""))

    @property
    def frames(self) -> h5py.Dataset:
        """The raw ``(N, rows, cols)`` frame dataset (read lazily)."""
        return self._f["frames/data"]

    @property
    def projection_indices(self) -> NDArray[np.intp]:
        """Indices of projection frames (image key 0)."""
        return np.flatnonzero(self.image_key == ImageKey.PROJECTION)

    def count_by_kind(self) -> dict[str, int]:
        """Frame counts per image key name."""
        return {k.label: int((self.image_key == k).sum()) for k in ImageKey}

    @property
    def time_s(self) -> NDArray[np.float64]:
        """Seconds since the scan started, per frame (NaN if not recorded)."""
        if "frames/time_s" not in self._f:
            return np.full(self.n_frames, np.nan)
        return np.asarray(self._f["frames/time_s"][: self.n_frames], dtype=float)

    def axes(self, kind: str = "encoders") -> dict[str, NDArray[np.float64]]:
        """Per-frame positions ``{'device.axis': (N,)}`` for ``encoders`` or ``commanded``."""
        if kind not in ("encoders", "commanded"):
            raise ScanFileError(f"axes kind must be 'encoders' or 'commanded', got {kind!r}")
        g = self._f.get(f"frames/{kind}")
        if g is None:
            return {}
        return {name: np.asarray(ds[: self.n_frames], dtype=float) for name, ds in g.items()}

    def attrs_json(self, group: str, key: str) -> Any:
        """Decode a JSON attribute (``{}`` when missing)."""
        g = self._f.get(group)
        if g is None or key not in g.attrs:
            return {}
        return json.loads(g.attrs[key])

    @property
    def orbit(self) -> tuple[str, dict[str, Any]]:
        """Orbit name and parameters."""
        name = str(self._f["orbit"].attrs.get("name", "")) if "orbit" in self._f else ""
        return name, self.attrs_json("orbit", "params_json")

    @property
    def marker_diameter_mm(self) -> float | None:
        """Nominal BB diameter, when the file states it."""
        g = self._f.get("markers")
        if g is None or "diameter_mm" not in g.attrs:
            return None
        return float(g.attrs["diameter_mm"])

    # ------------------------------------------------------------- geometry
    def has_geometry(self, name: str) -> bool:
        """Whether geometry ``nominal``, ``calibrated`` or ``truth`` is present."""
        return self._geometry_group(name) in self._f

    @staticmethod
    def _geometry_group(name: str) -> str:
        if name not in GEOMETRY_NAMES:
            raise ScanFileError(f"geometry must be one of {GEOMETRY_NAMES}, got {name!r}")
        return "truth/geometry" if name == "truth" else f"geometry/{name}"

    def geometry(self, name: str = "nominal") -> ViewGeometry:
        """Per-frame geometry (all N frames; non-projection rows are NaN)."""
        group = self._geometry_group(name)
        if group not in self._f:
            raise self._fail(f"has no /{group} (geometries present: {[g for g in GEOMETRY_NAMES if self.has_geometry(g)]})")
        return ViewGeometry(self._f[group]["vectors"][: self.n_frames], self.panel)

    # ---------------------------------------------------------------- pixels
    def _mean_of(self, key: ImageKey) -> NDArray[np.float32] | None:
        idx = np.flatnonzero(self.image_key == key)
        if idx.size == 0:
            return None
        acc = np.zeros(self.panel.shape, dtype=np.float64)
        for i in idx:
            acc += self.frames[int(i)]
        return (acc / idx.size).astype(np.float32)

    def dark_flat(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Mean dark and mean flat frames (dark 0 and flat = max of the projections when absent)."""
        if not hasattr(self, "_dark_flat"):
            dark = self._mean_of(ImageKey.DARK)
            flat = self._mean_of(ImageKey.FLAT)
            if dark is None:
                dark = np.zeros(self.panel.shape, dtype=np.float32)
            if flat is None:
                proj = self.projection_indices
                if proj.size == 0:
                    raise self._fail("has no flat frames and no projections to estimate a flat from")
                flat = np.full(self.panel.shape, float(np.max(self.frames[int(proj[0])])), dtype=np.float32)
            self._dark_flat = (dark, flat)
        return self._dark_flat

    def line_integrals(self, index: int) -> NDArray[np.float32]:
        """``-log((data - dark) / (flat - dark))`` of one frame, float32."""
        dark, flat = self.dark_flat()
        raw = np.asarray(self.frames[int(index)], dtype=np.float32)
        num = np.maximum(raw - dark, 0.5)
        den = np.maximum(flat - dark, 1.0)
        return (-np.log(num / den)).astype(np.float32)

    def iter_line_integrals(self, indices: Sequence[int] | None = None) -> Iterator[tuple[int, NDArray[np.float32]]]:
        """Stream ``(frame index, line-integral image)`` over projections (or the given frames)."""
        idx = self.projection_indices if indices is None else np.asarray(indices, dtype=int)
        for i in idx:
            yield int(i), self.line_integrals(int(i))

    def frame_problems(self, indices: Sequence[int] | None = None) -> dict[int, str]:
        """Frames that must not be used, with why: NaN or infinite pixels (any frame), and projections that are all
        zero (no signal) or saturated (more than half the pixels at the uint16 maximum). Reads each frame once."""
        idx = range(self.n_frames) if indices is None else [int(i) for i in indices]
        top = np.iinfo(np.uint16).max if self.frames.dtype == np.uint16 else None
        out: dict[int, str] = {}
        for i in idx:
            a = np.asarray(self.frames[i])
            if a.dtype.kind == "f":
                bad = int(a.size - np.count_nonzero(np.isfinite(a)))
                if bad:
                    out[i] = f"{bad} pixels NaN or infinite"
                    continue
            if self.image_key[i] != ImageKey.PROJECTION:
                continue
            if not a.any():
                out[i] = "all zero (no signal)"
            elif top is not None:
                frac = np.count_nonzero(a == top) / a.size
                if frac > 0.5:
                    out[i] = f"saturated ({frac:.0%} of pixels at {top})"
        return out

    # --------------------------------------------------------------- markers
    def markers(self) -> dict[str, NDArray[np.float64]]:
        """Whatever of ``uv``, ``xyz``, ``rpe_mm`` the file holds."""
        g = self._f.get("markers")
        if g is None:
            return {}
        return {k: np.asarray(g[k]) for k in ("uv", "xyz", "rpe_mm") if k in g}

    def truth_markers_xyz(self) -> NDArray[np.float64] | None:
        """True marker centres of a simulated scan."""
        ds = self._f.get("truth/markers/xyz")
        return None if ds is None else np.asarray(ds, dtype=float)

    @property
    def phantom(self) -> dict[str, Any]:
        """Phantom description of a simulated scan (``{}`` for real scans)."""
        return self.attrs_json("truth", "phantom_json")

    @property
    def h5(self) -> h5py.File:
        """The underlying h5py file, for extra groups this API does not cover."""
        return self._f

    def close(self) -> None:
        """Close the file."""
        self._f.close()

    def __enter__(self) -> "ScanFile":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"ScanFile({str(self.path)!r}, frames={self.n_frames}, status={self.status!r})"
