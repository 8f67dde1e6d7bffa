"""Synthetic geometries, markers and frames for calibration tests (independent of the simulator)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import Panel, ViewGeometry
from orbitct.rotations import rot_xyz
from orbitct.scanfile import ScanWriter

SAD, SDD, PANEL_MM = 785.0, 1200.0, 427.0


def detector(size: int) -> Panel:
    """Square detector with the default 427 mm panel."""
    return Panel(size, size, PANEL_MM / size, PANEL_MM / size)


def sawtooth(n: int, size: int) -> ViewGeometry:
    """Nominal sawtooth orbit: 360 deg rotation, tilt between +-20 deg, two cycles."""
    theta = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    phi = np.deg2rad(20.0) * (2.0 / np.pi) * np.arcsin(np.sin(2 * theta))
    return ViewGeometry.from_carm(theta, phi, SAD, SDD, detector(size))


def perturbed(nominal: ViewGeometry, seed: int = 0, angle_deg: float = 0.7, shift_mm: float = 8.0) -> ViewGeometry:
    """Nominal views moved rigidly like the paper's error profile (angle errors, 8 mm sine + 2 mm noise)."""
    rng = np.random.default_rng(seed)
    n = nominal.n_views
    s = np.linspace(0, 2 * np.pi, n)
    ang = np.deg2rad(angle_deg) * np.stack([np.sin(3 * s), np.cos(2 * s), np.sin(s + 1)], 1) + rng.normal(
        0, 0.001, (n, 3)
    )
    shift = shift_mm * np.stack([np.sin(s), np.cos(2 * s), 0.5 * np.sin(4 * s)], 1) + rng.uniform(-2, 2, (n, 3))
    R = rot_xyz(ang[:, 0], ang[:, 1], ang[:, 2])
    return nominal.transformed(R, shift)


def spiral_markers(k: int, radius: float = 70.0, height: float = 80.0) -> NDArray[np.float64]:
    """BB centres in a rough spiral on a cylinder surface."""
    a = np.linspace(0, 2 * np.pi, k, endpoint=False) * 1.37
    z = np.linspace(-height / 2, height / 2, k)
    return np.stack([radius * np.cos(a), radius * np.sin(a), z], 1)


def sphere_line_integrals(
    geometry: ViewGeometry, centres: NDArray[np.float64], radius_mm: float, mu_per_mm: float, oversample: int = 3
) -> NDArray[np.float32]:
    """Cone-beam line integrals of uniform spheres averaged over each pixel, ``(N, rows, cols)`` float32."""
    det = geometry.panel
    sub = (np.arange(oversample) + 0.5) / oversample - 0.5
    jj, ii = np.meshgrid(np.arange(det.cols * oversample), np.arange(det.rows * oversample))
    pix = np.stack([jj.ravel(), ii.ravel()], 1).astype(float) / oversample + sub[0]
    out = np.zeros((geometry.n_views, det.rows * det.cols * oversample**2), np.float32)
    for n in range(geometry.n_views):
        o, d = geometry[n].backproject(pix[None])
        o, d = o[0, 0], d[0]
        for c in centres:
            a = c - o
            along = d @ a
            dist2 = (a @ a) - along**2
            chord = 2.0 * np.sqrt(np.maximum(radius_mm**2 - dist2, 0.0))
            out[n] += (mu_per_mm * chord).astype(np.float32)
    out = out.reshape(geometry.n_views, det.rows, oversample, det.cols, oversample)
    return out.mean((2, 4))


def write_scan(
    path: Path,
    nominal: ViewGeometry,
    truth: ViewGeometry,
    markers: NDArray[np.float64],
    *,
    bb_diameter_mm: float = 3.17,
    clutter: NDArray[np.float64] | None = None,
    metal: NDArray[np.float64] | None = None,
    i0: float = 20000.0,
    seed: int = 0,
    diameter_attr: bool = True,
) -> Path:
    """A scan file with BBs (steel), a water cylinder, optional clutter spheres and metal balls; Poisson noise."""
    rng = np.random.default_rng(seed)
    det = nominal.panel
    with ScanWriter(path, det, marker_diameter_mm=bb_diameter_mm if diameter_attr else None, overwrite=True) as w:
        w.append(np.zeros(det.shape), "dark", 0.0)
        w.append(np.full(det.shape, i0), "flat", 0.0)
        for n in range(nominal.n_views):
            g = truth[n]
            li = sphere_line_integrals(g, markers, bb_diameter_mm / 2, 0.8)[0]
            li += sphere_line_integrals(g, np.array([[0.0, 0.0, 0.0]]), 75.0, 0.02, 1)[0]
            for c in clutter if clutter is not None else ():
                li += sphere_line_integrals(g, c[None, :3], float(c[3]), 0.01, 1)[0]
            for c in metal if metal is not None else ():
                li += sphere_line_integrals(g, c[None, :3], float(c[3]), 0.8, 1)[0]
            frame = rng.poisson(i0 * np.exp(-li)).astype(float)
            w.append(frame, "projection", float(n), nominal_vector=nominal.vectors[n])
        w.write_truth(np.concatenate([np.full((2, 12), np.nan), truth.vectors]), markers)
    return path


def assert_live_geometry_is_offline(out: Path, tmp_path: Path) -> None:
    """The geometry a live calibration wrote into the complete scan ``out`` is the one ``orbitct calibrate``
    computes from the same file, and within 1 px of the simulation truth."""
    import calib
    from calib.evaluate import similarity_aligned_error_px
    from orbitct.scanfile import ScanFile

    with ScanFile(out) as sf:
        assert sf.status == "complete" and sf.h5["geometry/calibrated"].attrs["live"]
        proj = sf.projection_indices
        live_geometry, truth = sf.geometry("calibrated")[proj], sf.geometry("truth")[proj]
    offline = calib.calibrate_scan(out, out=tmp_path / "offline.h5")
    np.testing.assert_array_equal(offline.geometry.vectors[proj], live_geometry.vectors)
    err, _ = similarity_aligned_error_px(live_geometry, truth)
    assert err < 1.0
