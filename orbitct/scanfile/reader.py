"""Validating reader for scan files; also adds calibration and reconstruction results."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbitct.geometry import Panel, GeometryError, ViewGeometry
from orbitct.scanfile.errors import ScanFileError
from orbitct.scanfile.writer import FORMAT, STATUSES, VERSION, _json

GEOMETRY_NAMES = ("nominal", "calibrated", "truth")


class ScanFile:
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
    def _fail(self, problem: str) -> ScanFileError:
        return ScanFileError(f"{self.path}: {problem}")

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
        bad = set(np.unique(keys).tolist()) - {0, 1, 2, 3}
        if bad:
            raise self._fail(f"/frames/image_key holds {sorted(bad)}, allowed are 0, 1, 2, 3")
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
        bad = np.flatnonzero((self.image_key == 0) & ~np.isfinite(v).all(axis=1))
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
        return np.flatnonzero(self.image_key == 0)

    def count_by_kind(self) -> dict[str, int]:
        """Frame counts per image key name."""
        names = {0: "projection", 1: "flat", 2: "dark", 3: "invalid"}
        return {names[k]: int((self.image_key == k).sum()) for k in names}

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
    def _mean_of(self, key: int) -> NDArray[np.float32] | None:
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
            dark = self._mean_of(2)
            flat = self._mean_of(1)
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

    # -------------------------------------------------------------- results
    def _writable(self) -> None:
        if self._f.mode != "r+":
            raise self._fail("opened read-only; open with mode='r+' to add results")

    def _replace(self, path: str, data: ArrayLike) -> h5py.Dataset:
        if path in self._f:
            del self._f[path]
        return self._f.create_dataset(path, data=data)

    def write_calibration(
        self,
        geometry: ViewGeometry,
        *,
        uv: ArrayLike,
        xyz: ArrayLike,
        rpe_mm: ArrayLike,
        method: str,
        iterations: int,
        elapsed_s: float,
        reproj_rms_px: float,
        extra_attrs: dict[str, Any] | None = None,
    ) -> None:
        """Store ``/geometry/calibrated`` and ``/markers/{uv,xyz,rpe_mm}``."""
        self._writable()
        if geometry.n_views != self.n_frames:
            raise self._fail(f"calibrated geometry has {geometry.n_views} views, the scan has {self.n_frames} frames")
        rpe = np.asarray(rpe_mm, dtype=float)
        self._replace("geometry/calibrated/vectors", geometry.vectors)
        self._replace("geometry/calibrated/matrices", geometry.matrices)
        g = self._f["geometry/calibrated"]
        ok = np.isfinite(rpe)
        g.attrs.update(
            {
                "method": method,
                "iterations": int(iterations),
                "elapsed_s": float(elapsed_s),
                "rpe_mean_mm": float(np.mean(rpe[ok])) if ok.any() else np.nan,
                "rpe_median_mm": float(np.median(rpe[ok])) if ok.any() else np.nan,
                "rpe_std_mm": float(np.std(rpe[ok])) if ok.any() else np.nan,
                "reproj_rms_px": float(reproj_rms_px),
            }
        )
        for k, v in (extra_attrs or {}).items():
            g.attrs[k] = _json(v) if isinstance(v, (dict, list)) else v
        self._f.require_group("markers")
        self._replace("markers/uv", np.asarray(uv, dtype=float))
        self._replace("markers/xyz", np.asarray(xyz, dtype=float))
        self._replace("markers/rpe_mm", rpe)
        self._f.flush()

    def write_recon(
        self,
        name: str,
        volume: ArrayLike,
        *,
        voxel_mm: Sequence[float],
        origin_mm: Sequence[float],
        algorithm: str,
        geometry: str,
        iterations: int,
        elapsed_s: float,
        params: dict[str, Any],
    ) -> None:
        """Store a reconstruction as ``/recon/<name>``."""
        self._writable()
        if not name or "/" in name:
            raise self._fail(f"reconstruction name {name!r} must be non-empty and contain no '/'")
        vol = np.asarray(volume, dtype=np.float32)
        if vol.ndim != 3:
            raise self._fail(f"volume must be 3-D (nz, ny, nx), got shape {vol.shape}")
        path = f"recon/{name}"
        if path in self._f:
            del self._f[path]
        g = self._f.create_group(path)
        g.create_dataset("volume", data=vol, chunks=(1,) + vol.shape[1:])
        g.attrs.update(
            {
                "voxel_mm": np.asarray(voxel_mm, dtype=float),
                "origin_mm": np.asarray(origin_mm, dtype=float),
                "algorithm": algorithm,
                "geometry": geometry,
                "iterations": int(iterations),
                "elapsed_s": float(elapsed_s),
                "params_json": _json(params),
            }
        )
        self._f.flush()

    def recon_names(self) -> list[str]:
        """Names of stored reconstructions."""
        return sorted(self._f["recon"].keys()) if "recon" in self._f else []

    def read_recon(self, name: str) -> tuple[NDArray[np.float32], dict[str, Any]]:
        """Volume and attributes of ``/recon/<name>``."""
        path = f"recon/{name}"
        if path not in self._f:
            raise self._fail(f"has no reconstruction {name!r} (present: {self.recon_names()})")
        g = self._f[path]
        attrs = {k: (v.tolist() if hasattr(v, "tolist") else v) for k, v in g.attrs.items()}
        return np.asarray(g["volume"], dtype=np.float32), attrs

    def set_status(self, status: str, reason: str = "") -> None:
        """Change ``/@status`` and ``/@status_reason``."""
        self._writable()
        if status not in STATUSES:
            raise self._fail(f"status must be one of {STATUSES}, got {status!r}")
        self._f.attrs["status"] = status
        self._f.attrs["status_reason"] = reason
        self._f.flush()

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
