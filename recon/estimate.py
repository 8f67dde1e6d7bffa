"""How long a reconstruction will take, estimated before anything large is allocated.

The projectors' cost grows with the number of rays (each set up, whether it meets the volume or not) and of ray
steps (per view, the pixels whose rays meet the volume times the planes they cross), FDK's with views x voxels, and reading the projections (each frame checked, its line integrals
formed) with views x pixels. The rates are measured once per process on small problems on this machine (the
reading on a small scan file written for it), so the estimate follows the machine and its load; it is an estimate
(caches behave differently at size). On a GPU (``device='cuda'``) the projectors' and FDK's rates are the GPU's,
measured the same way; small problems leave most of a GPU idle, so there the estimate errs long.
"""

from __future__ import annotations

import functools
import itertools
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from orbitct.geometry import ViewGeometry, VolumeGrid

_PROBE = 64  # voxels per side and pixels per side of the measuring problem
_PROBE_VIEWS = 8
_FDK_PROBE_VIEWS = 32
_READ_PROBE = 256  # pixels per side of the frames the reading rate is measured on


def _best(call: Callable[[], object]) -> float:
    times = []
    for _ in range(3):
        t = time.perf_counter()
        call()
        times.append(time.perf_counter() - t)
    return min(times)


@functools.cache
def projector_rates(device: str = "cpu") -> tuple[float, float, float, float]:
    """Seconds per ray and per ray step of the forward, then of the matched back projector: measured on a volume
    filling the field of view (every ray steps through it) and on a few voxels at its centre (nearly every ray
    misses them and costs only its set-up), the two costs solved from the two times."""
    from orbitct.reference_bench import PANEL_MM, SAD_MM, SDD_MM, reference_panel
    from recon.device import make_projector

    panel = reference_panel(_PROBE, PANEL_MM / _PROBE)
    geometry = ViewGeometry.from_carm(
        np.linspace(0.0, 2 * np.pi, _PROBE_VIEWS, endpoint=False), 0.0, SAD_MM, SDD_MM, panel
    )
    voxel = panel.pitch_col * SAD_MM / SDD_MM
    rays = float(geometry.n_views * panel.rows * panel.cols)
    times, counts = [], []
    for grid in (VolumeGrid.centered((_PROBE,) * 3, voxel), VolumeGrid.centered((4, 4, 4), voxel)):
        A = make_projector(grid, geometry, device)
        x = np.ones(grid.shape, np.float32)
        y = A(x)
        A.T(y)  # compiled before timing
        times.append((_best(functools.partial(A, x)), _best(functools.partial(A.T, y))))
        counts.append((rays, ray_steps(grid, geometry)))
    m = np.asarray(counts)
    out: list[float] = []
    for k in (0, 1):  # forward, back: per ray and per step from the two problems
        per_ray, per_step = np.linalg.solve(m, np.asarray([t[k] for t in times]))
        per_step = max(float(per_step), 0.0) or times[0][k] / m[0, 1]
        out += [max(float(per_ray), 0.0), per_step]
    return out[0], out[1], out[2], out[3]


@functools.cache
def rates(device: str = "cpu") -> tuple[float, float, float]:
    """Seconds per ray step of the forward and of the matched back projector, and per voxel and view of FDK."""
    _, forward, _, back = projector_rates(device)
    return forward, back, fdk_rate(device)


@functools.cache
def fdk_rate(device: str = "cpu") -> float:
    """Seconds per voxel and view of FDK (measured alone: an FDK's estimate compiles no projector on first use)."""
    from orbitct.reference_bench import PANEL_MM, SAD_MM, SDD_MM, reference_panel
    from recon.fdk import fdk

    panel = reference_panel(_PROBE, PANEL_MM / _PROBE)
    grid = VolumeGrid.centered((_PROBE,) * 3, panel.pitch_col * SAD_MM / SDD_MM)
    # FDK over 32 views: over 8 its fixed cost per call (filter set-up, allocation) weighed in, and the rate
    # overestimated a 128 x 192 x 192 reconstruction by half
    views = ViewGeometry.from_carm(
        np.linspace(0.0, 2 * np.pi, _FDK_PROBE_VIEWS, endpoint=False), 0.0, SAD_MM, SDD_MM, panel
    )
    y = np.ones((_FDK_PROBE_VIEWS, panel.rows, panel.cols), np.float32)
    fdk(y, grid, views, device=device)  # compiled before timing
    return _best(lambda: fdk(y, grid, views, device=device)) / (_FDK_PROBE_VIEWS * _PROBE**3)


@functools.cache
def reading_rate() -> float:
    """Seconds per projection pixel to read a scan's projections: each frame checked, then its line integrals
    formed (measured on a small scan file written to a temporary folder)."""
    from orbitct.reference_bench import SAD_MM, SDD_MM, reference_panel
    from orbitct.scanfile import ScanFile, ScanWriter

    rng = np.random.default_rng(0)
    panel = reference_panel(_READ_PROBE)
    views = ViewGeometry.from_carm(np.linspace(0.0, np.pi, _PROBE_VIEWS), 0.0, SAD_MM, SDD_MM, panel).vectors
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "probe.h5"
        with ScanWriter(path, panel, orbit_name="probe") as w:
            w.append(rng.poisson(100.0, panel.shape), "dark", 0.0)
            w.append(rng.poisson(2e4, panel.shape), "flat", 0.0)
            for vector in views:
                w.append(rng.poisson(5e3, panel.shape), "projection", 0.0, nominal_vector=vector)
        times = []
        for _ in range(3):
            with ScanFile(path) as sf:
                t = time.perf_counter()
                sf.frame_problems()
                for i in sf.projection_indices:
                    sf.line_integrals(int(i))
                times.append(time.perf_counter() - t)
    return min(times) / (_PROBE_VIEWS * _READ_PROBE**2)


def ray_steps(grid: VolumeGrid, geometry: ViewGeometry) -> float:
    """Ray steps of one projection of ``grid`` over ``geometry``'s views: per view, the pixels within the rectangle
    the volume's corners project into (the rays that meet it) times the planes along the main axis of the ray
    through its centre."""
    extent = grid.extent_mm
    corners = np.array(list(itertools.product(*extent)))  # (8, 3): x, y, z
    uv = geometry.project(corners)
    panel = geometry.panel
    with np.errstate(invalid="ignore"):
        u = np.clip(np.stack([np.nanmin(uv[..., 0], axis=1), np.nanmax(uv[..., 0], axis=1)]), -0.5, panel.cols - 0.5)
        v = np.clip(np.stack([np.nanmin(uv[..., 1], axis=1), np.nanmax(uv[..., 1], axis=1)]), -0.5, panel.rows - 0.5)
    hit = np.maximum(u[1] - u[0], 0.0) * np.maximum(v[1] - v[0], 0.0)
    towards = extent.mean(axis=1) - geometry.vectors[:, :3]
    nz, ny, nx = grid.shape
    planes = np.asarray((nx, ny, nz), dtype=float)[np.argmax(np.abs(towards), axis=1)]
    return float(np.nansum(hit * planes))


def reconstruction_seconds(
    algorithm: str,
    grid: VolumeGrid,
    n_views: int,
    rows: int,
    cols: int,
    iterations: int = 0,
    final_cost: bool = False,
    *,
    geometry: ViewGeometry | None = None,
    device: str = "cpu",
) -> float:
    """Estimated wall time of FDK, or of PWLS (its FDK start, the surrogate's set-up, ``iterations`` passes and, when
    asked for, the final cost) on this machine now, reading the projections included. With the projections'
    ``geometry`` the projectors count only the rays that meet the volume; without, every ray crosses half its
    planes along x and y. ``device``: where the projectors and FDK run (``cpu`` or ``cuda``)."""
    nz, ny, nx = grid.shape
    read_s = reading_rate() * n_views * rows * cols
    fdk_s = fdk_rate(device) * n_views * nz * ny * nx
    if algorithm == "fdk":
        return read_s + fdk_s
    forward, back, _ = rates(device)
    forward_ray, _, back_ray, _ = projector_rates(device)
    # a ray steps along its main axis, mostly x or y on C-arm orbits
    steps = ray_steps(grid, geometry) if geometry is not None else n_views * rows * cols * 0.5 * (nx + ny)
    rays = n_views * rows * cols  # each ray is set up whether it meets the volume or not
    passes = (iterations + 1, iterations + 1 + (1 if final_cost else 0))  # back, forward projections
    projecting_s = passes[1] * (rays * forward_ray + steps * forward) + passes[0] * (rays * back_ray + steps * back)
    return 2 * read_s + fdk_s + projecting_s


__all__ = [
    "fdk_rate",
    "projector_rates",
    "rates",
    "ray_steps",
    "reading_rate",
    "reconstruction_seconds",
]
