"""Results a scan file receives after acquisition: calibrated geometry, markers, reconstructions, status."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbitct.geometry import ViewGeometry
from orbitct.scanfile.errors import ScanFileError
from orbitct.scanfile.writer import STATUSES, to_json
from orbitct.statistics import rpe_statistics
from orbitct.verdict import Verdict


class ScanResults:
    """What :class:`~orbitct.scanfile.ScanFile` adds to an open file (``r+``) and reads back of it."""

    path: Path
    n_frames: int
    _f: h5py.File

    def _fail(self, problem: str) -> ScanFileError:
        return ScanFileError(f"{self.path}: {problem}")

    # -------------------------------------------------------------- results
    def _writable(self) -> None:
        if self._f.mode != "r+":
            raise self._fail("opened read-only; open with mode='r+' to add results")

    def _accepts_results(self) -> None:
        self._writable()
        self.refuse_if_acquiring()

    def refuse_if_acquiring(self) -> None:
        """Results go only into a finished scan: one still ``acquiring`` is being written, or was cut off."""
        if str(self._f.attrs.get("status", "complete")) == "acquiring":
            raise self._fail(
                "is still marked 'acquiring': its acquisition is running or was killed; results are "
                "added once it has ended (a file left by a killed acquisition: `orbitct scan repair` "
                "marks it aborted, keeping every frame)"
            )

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
        per_view: dict[str, ArrayLike] | None = None,
    ) -> None:
        """Store ``/geometry/calibrated`` (with ``per_view`` datasets beside the vectors, one row per frame) and
        ``/markers/{uv,xyz,rpe_mm}``."""
        self._accepts_results()
        if geometry.n_views != self.n_frames:
            raise self._fail(f"calibrated geometry has {geometry.n_views} views, the scan has {self.n_frames} frames")
        rpe = np.asarray(rpe_mm, dtype=float)
        self._replace("geometry/calibrated/vectors", geometry.vectors)
        self._replace("geometry/calibrated/matrices", geometry.matrices)
        g = self._f["geometry/calibrated"]
        g.attrs.update(
            {
                "method": method,
                "iterations": int(iterations),
                "elapsed_s": float(elapsed_s),
                **rpe_statistics(rpe).as_attrs(),
                "reproj_rms_px": float(reproj_rms_px),
            }
        )
        for k, v in (extra_attrs or {}).items():
            g.attrs[k] = to_json(v) if isinstance(v, (dict, list)) else v
        for name, values in (per_view or {}).items():
            arr = np.asarray(values)
            if arr.shape[:1] != (self.n_frames,):
                raise self._fail(f"calibrated {name} has {arr.shape[:1]} rows, the scan has {self.n_frames} frames")
            self._replace(f"geometry/calibrated/{name}", arr)
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
        overwrite: bool = False,
        verdict: Verdict | None = None,
    ) -> None:
        """Store a reconstruction as ``/recon/<name>`` (replacing one of that name only with ``overwrite``), with
        its quality ``verdict`` (:meth:`orbitct.verdict.Verdict.attrs`)."""
        self._accepts_results()
        if not name or "/" in name:
            raise self._fail(f"reconstruction name {name!r} must be non-empty and contain no '/'")
        vol = np.asarray(volume, dtype=np.float32)
        if vol.ndim != 3:
            raise self._fail(f"volume must be 3-D (nz, ny, nx), got shape {vol.shape}")
        path = f"recon/{name}"
        if path in self._f:
            if not overwrite:
                raise self._fail(f"already has a reconstruction named {name!r}")
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
                "params_json": to_json(params),
                **(verdict.attrs() if verdict is not None else {}),
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

    def set_live_calibration(self, outcome: str) -> None:
        """Say in ``/acquisition@live_calibration`` what became of a live calibration asked for with the scan:
        ``done``, or ``missing: <why>`` when it produced no geometry (``orbitct calibrate`` makes it from the file)."""
        self._writable()
        self._f.require_group("acquisition").attrs["live_calibration"] = outcome
        self._f.flush()

    @property
    def live_calibration(self) -> str:
        """``/acquisition@live_calibration``: ``done``, ``missing: <why>``, or '' when none was asked for."""
        group = self._f.get("acquisition")
        value = group.attrs.get("live_calibration", "") if isinstance(group, h5py.Group) else ""
        return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)
