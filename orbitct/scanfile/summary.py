"""The one summary of a scan file: what ``orbitct inspect`` prints and the REST service reports."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from orbitct.verdict import Verdict

if TYPE_CHECKING:
    from orbitct.scanfile.reader import ScanFile

T = TypeVar("T")


def _finite(value: Any) -> float | None:
    v = float(value)
    return v if np.isfinite(v) else None


def taken_off_command(f: ScanFile) -> dict[str, dict[str, Any]]:
    """Per axis, the projections read back further from their commanded position than one step of that axis between
    projections (the median of its steps): frames taken where their nominal geometry does not say (a sweep that ran
    ahead of its exposures). ``{axis: {"frames", "max", "step", "unit"}}``, only for axes with such frames."""
    idx = f.projection_indices
    encoders, commanded = f.axes("encoders"), f.axes("commanded")
    out: dict[str, dict[str, Any]] = {}
    for axis, values in commanded.items():
        if axis not in encoders or idx.size < 2:
            continue
        cmd, read = values[idx], encoders[axis][idx]
        steps = np.abs(np.diff(cmd))
        steps = steps[np.isfinite(steps) & (steps > 1e-9)]
        if steps.size == 0:
            continue
        step = float(np.median(steps))
        off = np.abs(read - cmd)
        far = np.isfinite(off) & (off > step)
        if far.any():
            unit = str(f.h5[f"frames/encoders/{axis}"].attrs.get("unit", ""))
            out[axis] = {"frames": int(far.sum()), "max": float(off[far].max()), "step": step, "unit": unit}
    return out


def _read(damage: list[str], what: str, read: Callable[[], T], default: T) -> T:
    """``read()``, or ``default`` when that part of the file is damaged (said in ``damage``)."""
    from orbitct.scanfile.reader import HDF5_ERRORS, _hdf5_text

    try:
        return read()
    except HDF5_ERRORS as exc:
        damage.append(f"{what} cannot be read ({_hdf5_text(exc)})")
        return default


def scan_summary(f: ScanFile) -> dict[str, Any]:
    """JSON-ready summary of an open scan file: status, frames by kind, panel, orbit, geometries, markers, results.
    A part that the file's damage makes unreadable (one that opening the file does not check) is left out and named
    in ``damaged``; what calibration and reconstruction need is checked when the file opens."""
    damage: list[str] = []
    summary = _summary(f, damage)
    summary["damaged"] = damage
    return summary


def _summary(f: ScanFile, damage: list[str]) -> dict[str, Any]:
    panel = f.panel
    name, params = f.orbit
    orbit: dict[str, Any] = {"name": name, "params": params}
    idx = f.projection_indices
    if f.has_geometry("nominal") and idx.size:
        S = f.geometry("nominal").S[idx]
        d = S / np.linalg.norm(S, axis=1, keepdims=True)
        rot = np.degrees(np.unwrap(np.arctan2(d[:, 0], -d[:, 1])))
        tilt = np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))
        orbit["rotation_deg"] = [float(rot.min()), float(rot.max())]
        orbit["tilt_deg"] = [float(tilt.min()), float(tilt.max())]
    calibration: dict[str, Any] = {}
    if f.has_geometry("calibrated"):

        def calibrated() -> dict[str, Any]:
            a = f.h5["geometry/calibrated"].attrs
            out: dict[str, Any] = {
                k: (_finite(a[k]) if k != "method" else str(a[k]))
                for k in ("method", "rpe_mean_mm", "rpe_median_mm", "rpe_std_mm", "reproj_rms_px")
                if k in a
            }
            verdict = Verdict.from_attrs(a)
            if verdict is None and "quality" in a:  # written before verdicts: passed or failed, its reasons
                verdict = Verdict(reasons=("quality check failed",) if str(a["quality"]) == "failed" else ())
            if verdict is not None:
                out["verdict"] = verdict.summary()
            return out

        calibration = _read(damage, "/geometry/calibrated's attributes", calibrated, {})
    markers: dict[str, Any] = _read(damage, "/markers", f.markers, {})
    truth = _read(damage, "/truth/markers/xyz", f.truth_markers_xyz, None)
    ph: dict[str, Any] = _read(damage, "/truth@phantom_json", lambda: f.phantom, {})
    times = _read(damage, "/frames/time_s", lambda: f.time_s, np.full(f.n_frames, np.nan))
    live = _read(damage, "/acquisition@live_calibration", lambda: f.live_calibration, "")
    return {
        "status": f.status,
        "status_reason": f.status_reason,
        "n_frames": f.n_frames,
        "frames_without_pixels": f.frames_without_pixels,
        "frames_by_kind": f.count_by_kind(),
        "taken_off_command": _read(
            damage, "/frames/encoders or /frames/commanded", lambda: taken_off_command(f), dict[str, dict[str, Any]]()
        ),
        "dtype": str(f.frames.dtype),
        "detector": {"rows": panel.rows, "cols": panel.cols, "pitch_mm": list(panel.pitch_mm)},
        "duration_s": float(np.nanmax(times)) if f.n_frames and np.isfinite(times).any() else None,
        "orbit": orbit,
        "geometries": [g for g in ("nominal", "calibrated", "truth") if f.has_geometry(g)],
        "calibration": calibration,
        "live_calibration": {"outcome": live} if live else {},
        "markers": {
            "diameter_mm": f.marker_diameter_mm,
            "detected": int(markers["uv"].shape[1]) if "uv" in markers else 0,
            "estimated": int(markers["xyz"].shape[0]) if "xyz" in markers else 0,
            "truth": int(truth.shape[0]) if truth is not None else 0,
        },
        "phantom": (f"{ph.get('name', '')}: {len(ph.get('primitives', []))} primitives" if ph else ""),
        "recon": _read(damage, "/recon", f.recon_names, list[str]()),
        "import_assumptions": _read(
            damage,
            "/provenance@import_assumptions_json",
            lambda: list(f.attrs_json("provenance", "import_assumptions_json").get("assumed", [])),
            [],
        ),
        "file_bytes": f.path.stat().st_size,
        # a linked file (orbitct calibrate --out) reads its frames from this scan file; None: it holds its own
        "frames_file": None if f.frames_file == f.path else str(f.frames_file),
        "ignored": list(f.warnings),
    }
