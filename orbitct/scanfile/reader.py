"""Validating reader for scan files (``docs/scan-file.md``)."""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from orbitct.defects import DefectMap
from orbitct.geometry import GeometryError, Panel, ViewGeometry
from orbitct.scanfile.errors import ScanFileError
from orbitct.scanfile.keys import ImageKey
from orbitct.scanfile.linked import frames_source, linked_frames_problem
from orbitct.scanfile.results import ScanResults
from orbitct.scanfile.writer import FORMAT, STATUSES, VERSION

GEOMETRY_NAMES = ("nominal", "calibrated", "truth")
FRAME_COPIES = 12  # float64 copies of a frame that detection and reconstruction hold at once (per worker)
log = logging.getLogger("orbitct.scanfile")
_WARNED: set[tuple[str, str]] = set()  # (file, warning) said already in this process
#: what h5py raises on a damaged file (a broken heap, B-tree or object header, a link loop, a chunk past the end;
#: SystemError when a callback inside HDF5's iteration met a damaged name that is not UTF-8)
HDF5_ERRORS = (OSError, RuntimeError, KeyError, ValueError, TypeError, SystemError)


def _hdf5_text(exc: BaseException) -> str:
    """HDF5's own words for a failure, without h5py's prefixes and the call chain."""
    text = str(exc.args[0] if isinstance(exc, KeyError) and exc.args else exc).splitlines()[0] if str(exc) else ""
    inner = text[text.find("(") + 1 : text.rfind(")")] if "(" in text and text.endswith(")") else text
    return (inner or type(exc).__name__)[:160]


def damaged(path: Path, exc: BaseException) -> ScanFileError:
    """The one sentence for a file HDF5 cannot read further: damaged, where HDF5 says."""
    return ScanFileError(
        f"{path}: the file is damaged and cannot be read ({_hdf5_text(exc)}); an intact copy, or "
        "`orbitct scan repair` for a scan whose acquisition was cut short, may help"
    )


def describe_frame_problems(problems: dict[int, str], shown: int = 5) -> str:
    """The first ``shown`` problems as ``frame 12 (why), ...`` and how many more, for one-line messages."""
    items = sorted(problems.items())
    more = f" and {len(items) - shown} more" if len(items) > shown else ""
    return ", ".join(f"frame {i} ({why})" for i, why in items[:shown]) + more


def frame_problem(frame: NDArray[Any], projection: bool) -> str | None:
    """Why a frame must not be used, or None: NaN or infinite pixels (any frame); a projection with no pixel above
    zero (no signal) or saturated (more than half its pixels at the uint16 maximum)."""
    if frame.dtype.kind == "f":
        bad = int(frame.size - np.count_nonzero(np.isfinite(frame)))
        if bad:
            return f"{bad} pixels NaN or infinite"
    if not projection:
        return None
    top = frame.max() if frame.size else 0  # one pass, no temporary: most frames need no other
    if not top > 0:
        return "all zero (no signal)" if not frame.any() else "no pixel above zero (no signal)"
    if frame.dtype == np.uint16 and top == 65535:
        frac = np.count_nonzero(frame == 65535) / frame.size
        if frac > 0.5:
            return f"saturated ({frac:.0%} of pixels at 65535)"
    return None


def _shown(value: Any) -> str:
    """An attribute value as a person reads it (no numpy reprs)."""
    if isinstance(value, np.ndarray):
        return str(value.tolist())
    if isinstance(value, np.generic):
        return repr(value.item())
    return repr(value)


def _integer(value: Any) -> int:
    """An integer attribute (a float that is whole is accepted; text, arrays and fractions are not)."""
    if isinstance(value, (bytes, str)) or np.ndim(value) != 0:
        raise ValueError(value)
    number = float(value)
    if not number.is_integer():
        raise ValueError(value)
    return int(number)


def _degenerate_views(v: NDArray[np.float64], proj: NDArray[np.bool_]) -> dict[str, NDArray[np.intp]]:
    """Projection views no camera can have: zero or parallel detector axes, a source in the detector plane."""
    S, D, u, v_ = v[:, 0:3], v[:, 3:6], v[:, 6:9], v[:, 9:12]
    nu, nv = np.linalg.norm(u, axis=1), np.linalg.norm(v_, axis=1)
    n = np.cross(u, v_)
    nn = np.linalg.norm(n, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = np.abs(np.einsum("ij,ij->i", S - D, n)) / nn
    out: dict[str, NDArray[np.intp]] = {}
    checks = {
        "a detector axis has zero length": (nu == 0) | (nv == 0),
        "the detector axes u and v are parallel": (nu > 0) & (nv > 0) & (nn <= 1e-9 * nu * nv),
        "the source lies in the detector plane": (nn > 1e-9 * nu * nv) & ~(height > 1e-6),
    }
    for why, hit in checks.items():
        frames = np.flatnonzero(proj & hit)
        if frames.size:
            out[why] = frames
    return out


def frames_with_pixels(data: h5py.Dataset, n: int, file_bytes: int, look_back: int = 8) -> int:
    """How many of the first ``n`` frames have their pixels in the file. A disk that fills up while a frame is
    written can leave the frame counted with no data chunk, or with one past the end of the file; only the
    last ``look_back`` frames are looked at (frames are written in order). Frames stored one per chunk only."""
    if n == 0 or data.chunks is None or data.chunks[0] != 1 or data.shape[0] < n:
        return n
    k = n
    while k > 0 and n - k < look_back:
        try:
            info = data.id.get_chunk_info_by_coord((k - 1,) + (0,) * (data.ndim - 1))
        except (RuntimeError, ValueError, AttributeError):
            return n  # this HDF5 cannot tell
        if info.byte_offset is not None and info.byte_offset + info.size <= file_bytes:
            break
        k -= 1
    return k


class ScanFile(ScanResults):
    """An open scan file, checked against ``scan-file.md`` on open. Use as a context manager.

    Data stored outside the file (external links, raw external storage, virtual datasets) is refused unless
    ``allow_external``: the file alone must be the record of the scan.
    """

    def __init__(self, path: str | os.PathLike[str], mode: str = "r", *, allow_external: bool = False) -> None:
        self.path = Path(path)
        self.allow_external = allow_external
        self.warnings: list[str] = []  # what was ignored in this file, and why
        self.frames_file = self.path  # where the frames' pixels are (another scan file: see orbitct.scanfile.linked)
        self._frames_h5: h5py.File | None = None
        if mode not in ("r", "r+"):
            raise ScanFileError(f"{self.path}: mode must be 'r' or 'r+', got {mode!r}")
        if not self.path.is_file():
            raise ScanFileError(f"{self.path}: no such file")
        try:
            self._f = h5py.File(self.path, mode)
        except OSError as exc:
            raise ScanFileError(f"{self.path}: not a readable HDF5 file ({exc})") from None
        try:
            self._check_links()
            self._validate()
        except ScanFileError:
            self._f.close()
            raise
        except HDF5_ERRORS as exc:  # a damaged heap, B-tree or object header, or a link loop, met on the way
            self._f.close()
            raise damaged(self.path, exc) from None

    # ------------------------------------------------------------ validation
    def _check_links(self) -> None:
        """Every object of the file reachable and every soft link resolving to one (no dangling link, no loop): what
        any command may read later must not fail there. Hard links are ordinary HDF5 (a group may contain itself)."""
        problems: list[str] = []

        def visit(name: str, link: Any) -> None:
            if len(problems) >= 3:
                return
            if isinstance(link, h5py.SoftLink):
                try:
                    target = self._f.get(name)
                except HDF5_ERRORS as exc:
                    problems.append(
                        f"/{name} is a soft link to {link.path} that goes round in a loop or cannot be "
                        f"followed ({_hdf5_text(exc)})"
                    )
                    return
                if target is None:
                    problems.append(f"/{name} is a soft link to {link.path}, which does not exist")

        self._f.visititems_links(visit)
        if problems:
            raise self._fail("; ".join(problems))

    def _validate(self) -> None:
        f = self._f
        fmt = f.attrs.get("format")
        if fmt is None:
            raise self._fail(f"not an orbitct scan file (an HDF5 file without the /@format attribute {FORMAT!r})")
        if fmt != FORMAT:
            raise self._fail(f"not an orbitct scan file (format tag is {_shown(fmt)}, expected {FORMAT!r})")
        ver = f.attrs.get("version")
        try:
            ok_version = ver is not None and int(ver) == VERSION
        except (TypeError, ValueError):
            ok_version = False
        if not ok_version:
            got = "has no /@version attribute" if ver is None else f"is version {_shown(ver)}"
            raise self._fail(f"{got}; this reader supports version {VERSION}")
        status = f.attrs.get("status", "complete")
        if status not in STATUSES:
            raise self._fail(f"status is {_shown(status)}, expected one of {', '.join(STATUSES)}")
        if "detector" not in f:
            raise self._fail("missing group /detector")
        da = f["detector"].attrs
        for key in ("rows", "cols", "pitch_mm"):
            if key not in da:
                raise self._fail(f"missing attribute /detector@{key}")
        try:
            pitch = np.asarray(da["pitch_mm"], dtype=float).ravel()
            rows, cols = _integer(da["rows"]), _integer(da["cols"])
        except (TypeError, ValueError):
            raise self._fail(
                f"/detector@rows, cols and pitch_mm must be numbers, got {_shown(da['rows'])}, "
                f"{_shown(da['cols'])}, {_shown(da['pitch_mm'])}"
            ) from None
        if pitch.shape != (2,):
            raise self._fail(f"/detector@pitch_mm must hold 2 numbers [col, row], got {pitch.tolist()}")
        try:
            self.panel = Panel(rows, cols, float(pitch[0]), float(pitch[1]))
        except GeometryError as exc:
            raise self._fail(f"/detector attributes: {exc}") from None
        linked = linked_frames_problem(self.path, f)
        if linked is not None:
            raise self._fail(linked)
        self.frames_file = frames_source(self.path, f)
        for ds in ("frames/data", "frames/image_key"):
            self._dataset(ds)
        data, key = f["frames/data"], f["frames/image_key"]
        if data.ndim != 3 or data.shape[1:] != self.panel.shape:
            raise self._fail(f"/frames/data has shape {data.shape}, expected (N, {self.panel.rows}, {self.panel.cols})")
        if data.dtype not in (np.uint16, np.float32):
            raise self._fail(f"/frames/data has dtype {data.dtype}, expected uint16 or float32")
        if key.ndim != 1 or key.dtype.kind not in "iu":
            raise self._fail(f"/frames/image_key must be 1-D integers, got shape {key.shape} of {key.dtype}")
        lengths = {"/frames/data": data.shape[0], "/frames/image_key": key.shape[0]}
        if "frames/time_s" in f:
            t = self._dataset("frames/time_s")
            if t.ndim != 1 or t.dtype.kind not in "fiu":
                raise self._fail(f"/frames/time_s must be 1-D numbers, got shape {t.shape} of {t.dtype}")
            lengths["/frames/time_s"] = t.shape[0]
        if status == "acquiring":
            n = min(lengths.values())  # a scan still being written, or one that crashed
        else:
            if len(set(lengths.values())) != 1:
                raise self._fail(f"per-frame datasets disagree in length: {lengths}")
            n = data.shape[0]
        complete = frames_with_pixels(data, int(n), self.path.stat().st_size)
        # frames counted at the end whose pixels never reached the file (the disk filled up): left out
        self.frames_without_pixels = int(n) - complete
        self.n_frames = complete
        keys = key[: self.n_frames]
        bad = set(np.unique(keys).tolist()) - {int(k) for k in ImageKey}
        if bad:
            raise self._fail(
                f"/frames/image_key holds {sorted(bad)}, allowed are {', '.join(str(k.value) for k in ImageKey)} "
                f"({', '.join(k.label for k in ImageKey)})"
            )
        self.image_key: NDArray[np.int8] = np.asarray(keys, dtype=np.int8)
        for name in ("nominal", "calibrated"):
            if f"geometry/{name}" in f:
                self._check_geometry(f"geometry/{name}")
        if "truth/geometry" in f:
            self._check_geometry("truth/geometry")
        for group, key in (("orbit", "params_json"), ("provenance", "config_json"), ("truth", "phantom_json")):
            self.attrs_json(group, key)
        if "markers" in f and "diameter_mm" in f["markers"].attrs:
            d = f["markers"].attrs["diameter_mm"]
            try:
                ok = np.ndim(d) == 0 and np.isfinite(float(d)) and float(d) > 0
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise self._fail(f"/markers@diameter_mm must be a positive number of millimetres, got {_shown(d)}")

    def _dataset(self, path: str) -> h5py.Dataset:
        """The dataset at ``path``: present, a dataset, and stored in this file (unless :attr:`allow_external`)."""
        parts = path.split("/")
        for depth in range(1, len(parts) + 1):
            sub = "/".join(parts[:depth])
            link = self._f.get(sub, getlink=True)
            if link is None:
                raise self._fail(f"missing dataset /{path}")
            if isinstance(link, h5py.ExternalLink) and not self.allow_external:
                raise self._fail(
                    f"/{sub} is a link into another file ({link.filename}); a scan file must hold its "
                    "own data (Python: ScanFile(..., allow_external=True) if that is intended)"
                )
        ds = self._f[path]
        if not isinstance(ds, h5py.Dataset):
            raise self._fail(f"/{path} must be a dataset, found a {type(ds).__name__.lower()}")
        checked_link = path == "frames/data" and self.frames_file != self.path  # the scan it names: checked
        if not self.allow_external and (ds.external or (ds.is_virtual and not checked_link)):
            where = "raw external files" if ds.external else "other files (a virtual dataset)"
            raise self._fail(
                f"/{path} is stored in {where}; a scan file must hold its own data "
                "(Python: ScanFile(..., allow_external=True) if that is intended)"
            )
        return ds

    def _check_geometry(self, group: str) -> None:
        g = self._f[group]
        if not isinstance(g, h5py.Group):
            raise self._fail(f"/{group} must be a group")
        vec = self._dataset(f"{group}/vectors")
        if vec.ndim != 2 or vec.shape[1] != 12 or vec.shape[0] < self.n_frames or vec.dtype.kind not in "fiu":
            raise self._fail(
                f"/{group}/vectors has shape {vec.shape} of {vec.dtype}, expected ({self.n_frames}, 12) numbers"
            )
        if "matrices" in g and (g["matrices"].shape[1:] != (3, 4) or g["matrices"].shape[0] < self.n_frames):
            raise self._fail(f"/{group}/matrices has shape {g['matrices'].shape}, expected ({self.n_frames}, 3, 4)")
        if group == "geometry/calibrated":
            return  # calibration may leave NaN for views it could not solve
        v = np.asarray(vec[: self.n_frames])
        proj = self.image_key == ImageKey.PROJECTION
        bad = np.flatnonzero(proj & ~np.isfinite(v).all(axis=1))
        if bad.size:
            raise self._fail(
                f"/{group}/vectors is not finite on projection frames {bad[:5].tolist()}"
                + (" ..." if bad.size > 5 else "")
            )
        for why, frames in _degenerate_views(v, proj).items():
            raise self._fail(
                f"/{group}/vectors: {why} on projection frames {frames[:5].tolist()}"
                + (" ..." if frames.size > 5 else "")
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
        """The raw ``(N, rows, cols)`` frame dataset (read lazily); a linked file's from the scan it names, opened
        read-only whatever this file's mode (HDF5 would open it as this file is)."""
        if self.frames_file == self.path:
            return self._f["frames/data"]
        if self._frames_h5 is None:
            self._frames_h5 = h5py.File(self.frames_file, "r")
        return self._frames_h5["frames/data"]

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
        """Decode a JSON object attribute (``{}`` when missing). None of these is needed to calibrate or reconstruct:
        one that is not a JSON object (another writer's list, text that is not JSON) is ignored with a warning."""
        g = self._f.get(group)
        if g is None or key not in g.attrs:
            return {}
        raw = g.attrs[key]
        try:
            value = json.loads(raw.decode("utf-8") if isinstance(raw, bytes) else raw)
        except (TypeError, ValueError, UnicodeDecodeError):
            self._ignore(f"/{group}@{key}", "is not valid JSON")
            return {}
        if not isinstance(value, dict):
            kind = {list: "a list", str: "text", int: "a number", float: "a number", bool: "true or false"}.get(
                type(value), "null"
            )
            self._ignore(f"/{group}@{key}", f"is JSON {kind}, not an object")
            return {}
        return value

    def _ignore(self, where: str, why: str) -> None:
        """Say once that ``where`` is ignored (:attr:`warnings`, and the log once per process and file)."""
        text = (
            f"{self.path.name}: {where} {why}; it is ignored (nothing that orbitct calibrates or reconstructs needs it)"
        )
        if text not in self.warnings:
            self.warnings.append(text)
        if (str(self.path), text) not in _WARNED:
            _WARNED.add((str(self.path), text))
            log.warning("%s", text)

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
            raise self._fail(
                f"has no /{group} (geometries present: {[g for g in GEOMETRY_NAMES if self.has_geometry(g)]})"
            )
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

    def defects(self) -> DefectMap:
        """The panel's pixels that do not respond to X-rays in this scan's darks and flats (:mod:`orbitct.defects`)."""
        if not hasattr(self, "_defects"):
            self._defects = DefectMap.from_dark_flat(*self.dark_flat())
        return self._defects

    def line_integrals(self, index: int) -> NDArray[np.float32]:
        """``-log((data - dark) / (flat - dark))`` of one frame, float32; defective pixels filled from their row
        neighbours (:meth:`defects`)."""
        dark, flat = self.dark_flat()
        raw = np.asarray(self.frames[int(index)], dtype=np.float32)
        num = np.maximum(raw - dark, 0.5)
        den = np.maximum(flat - dark, 1.0)
        return self.defects().filled((-np.log(num / den)).astype(np.float32))

    def iter_line_integrals(self, indices: Sequence[int] | None = None) -> Iterator[tuple[int, NDArray[np.float32]]]:
        """Stream ``(frame index, line-integral image)`` over projections (or the given frames)."""
        idx = self.projection_indices if indices is None else np.asarray(indices, dtype=int)
        for i in idx:
            yield int(i), self.line_integrals(int(i))

    def frame_problems(self, indices: Iterable[int] | None = None) -> dict[int, str]:
        """Frames that must not be used, with why (:func:`frame_problem`); reads each frame once."""
        idx = range(self.n_frames) if indices is None else [int(i) for i in indices]
        out: dict[int, str] = {}
        for i in idx:
            try:
                frame = np.asarray(self.frames[i])
            except HDF5_ERRORS as exc:
                out[i] = f"cannot be read: {_hdf5_text(exc)}"
                continue
            why = frame_problem(frame, self.image_key[i] == ImageKey.PROJECTION)
            if why is not None:
                out[i] = why
        return out

    def unusable_because(self, check_pixels: bool = True) -> list[str]:
        """Why neither ``orbitct calibrate`` nor ``orbitct reconstruct`` can use this file (empty when one can): still
        acquiring, no projections, no geometry, frames too large for this machine, or (``check_pixels``, reading every
        frame once) frames with NaN, infinite or no signal."""
        reasons = []
        if self.status == "acquiring":
            reasons.append(
                "its status is 'acquiring' (still being written, or left by an acquisition that died): "
                "`orbitct scan repair` marks it aborted, keeping its frames"
            )
        proj = self.projection_indices
        if proj.size == 0:
            counts = ", ".join(f"{n} {k}" for k, n in self.count_by_kind().items() if n) or "none"
            reasons.append(f"it has no projection frames (image_key 0; frames: {counts})")
        if not (self.has_geometry("nominal") or self.has_geometry("calibrated")):
            reasons.append(
                "it has no geometry (neither /geometry/nominal nor /geometry/calibrated) to reconstruct "
                "or calibrate from"
            )
        import psutil

        frame_bytes = self.panel.rows * self.panel.cols * 8
        available = psutil.virtual_memory().available
        if frame_bytes * FRAME_COPIES > available // 2:
            reasons.append(
                f"a frame of {self.panel.rows} x {self.panel.cols} pixels needs about "
                f"{frame_bytes * FRAME_COPIES / 2**30:.1f} GiB to process and {available / 2**30:.1f} GiB "
                "is available"
            )
        elif check_pixels and not reasons:
            needed = np.union1d(proj, np.flatnonzero(np.isin(self.image_key, (ImageKey.DARK, ImageKey.FLAT))))
            problems = self.frame_problems(needed.tolist())
            if problems:
                reasons.append(f"frames are unusable: {describe_frame_problems(problems)}")
        return reasons

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
        """Close the file (and the scan a linked file reads its frames from)."""
        if self._frames_h5 is not None:
            self._frames_h5.close()
        self._f.close()

    def __enter__(self) -> ScanFile:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"ScanFile({str(self.path)!r}, frames={self.n_frames}, status={self.status!r})"
