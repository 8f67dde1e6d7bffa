"""Helpers for reconstruction tests: analytic sphere phantoms, the bench panel, small scan files.

A uniquely named module (not ``conftest``): test folders each have a conftest, and
``from conftest import`` picks whichever was imported first in a whole-suite run.
"""

from __future__ import annotations

import numpy as np

from orbitct.geometry import Panel, ViewGeometry
from recon import VolumeGrid

SPHERES = [((0.0, 0.0, 0.0), 60.0, 0.02), ((20.0, 10.0, 5.0), 15.0, 0.01), ((-25.0, -5.0, -10.0), 10.0, 0.03)]


def sphere_line_integrals(g: ViewGeometry, spheres=SPHERES) -> np.ndarray:
    """Exact line integrals of a sum of uniform spheres through every pixel centre."""
    det = g.panel
    cols, rows = np.meshgrid(np.arange(det.cols), np.arange(det.rows))
    px = np.stack([cols.ravel(), rows.ravel()], 1).astype(float)
    o, d = g.backproject(px)
    out = np.zeros((g.n_views, det.rows * det.cols))
    for c, r, mu in spheres:
        oc = o - np.asarray(c)
        b = np.einsum("nkj,nkj->nk", d, np.broadcast_to(oc, d.shape))
        disc = b**2 - (np.sum(oc**2, -1) - r * r)
        out += mu * 2 * np.sqrt(np.clip(disc, 0, None))
    return out.reshape(g.n_views, det.rows, det.cols).astype(np.float32)


def voxelized_spheres(grid: VolumeGrid, spheres=SPHERES, supersample: int = 3) -> np.ndarray:
    """Spheres sampled on the grid (supersampled partial-volume average)."""
    z, y, x = grid.coords_mm()
    vx, vy, vz = grid.voxel_mm
    off = (np.arange(supersample) + 0.5) / supersample - 0.5
    vol = np.zeros(grid.shape)
    for oz in off:
        for oy in off:
            for ox in off:
                zz, yy, xx = np.meshgrid(z + oz * vz, y + oy * vy, x + ox * vx, indexing="ij")
                for c, r, mu in spheres:
                    vol += mu * ((xx - c[0]) ** 2 + (yy - c[1]) ** 2 + (zz - c[2]) ** 2 < r * r)
    return (vol / supersample**3).astype(np.float32)


def bench_detector(size: int) -> Panel:
    """The default 427 mm panel sampled with ``size`` x ``size`` pixels."""
    return Panel(size, size, 427.0 / size, 427.0 / size)


def write_sphere_scan(
    path,
    geometry: ViewGeometry,
    *,
    truth: ViewGeometry | None = None,
    i0: float = 2e4,
    spheres=SPHERES,
    seed: int = 0,
    n_flat: int = 2,
    n_dark: int = 2,
) -> None:
    """A small scan file of analytic spheres: darks, flats, Poisson projections, nominal (+ truth) geometry."""
    from orbitct.scanfile import ScanWriter

    rng = np.random.default_rng(seed)
    det = geometry.panel
    seen = truth if truth is not None else geometry
    li = sphere_line_integrals(seen, spheres)
    dark = 100.0
    with ScanWriter(path, det, orbit_name="test", overwrite=True) as w:
        t = 0.0
        for _ in range(n_dark):
            w.append(rng.poisson(dark, det.shape), "dark", t)
            t += 0.1
        for _ in range(n_flat):
            w.append(rng.poisson(i0, det.shape) + dark, "flat", t)
            t += 0.1
        for k in range(geometry.n_views):
            w.append(rng.poisson(i0 * np.exp(-li[k])) + dark, "projection", t, nominal_vector=geometry.vectors[k])
            t += 0.1
        if truth is not None:
            nan = np.full((n_dark + n_flat, 12), np.nan)
            w.write_truth(
                np.concatenate([nan, truth.vectors]),
                phantom={"spheres": [list(map(float, (*c, r, m))) for c, r, m in spheres]},
            )
        w.finish("complete")
