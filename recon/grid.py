"""Which volume grid a reconstruction uses: the field of view of the views, and checks against it."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry, VolumeGrid
from recon.errors import FieldOfViewError


def views_isocenter(geometry: ViewGeometry) -> NDArray[np.float64]:
    """Least-squares point closest to every view's central ray (source to detector centre)."""
    d = geometry.D - geometry.S
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    return np.linalg.lstsq(proj.sum(0), np.einsum("nij,nj->i", proj, geometry.S), rcond=None)[0]


def fov_radius_height(geometry: ViewGeometry) -> tuple[float, float, tuple[float, float, float]]:
    """Radius and height (mm) of the cylinder about +z seen by every valid view, and its centre."""
    g = geometry[np.flatnonzero(geometry.valid)]
    det = g.panel
    sod = g.sod()
    mag = g.sdd / sod
    half_w = (det.cols * det.pitch_col) / 2 / mag
    half_h = (det.rows * det.pitch_row) / 2 / mag
    # the circle seen by a full rotation: distance from the axis to the fan edge
    radius = float(np.min(sod * np.sin(np.arctan(half_w / sod))))
    height = float(np.min(2 * half_h * (1 - radius / sod)))
    center = views_isocenter(g)
    return radius, height, (float(center[0]), float(center[1]), float(center[2]))


def grid_for_geometry(
    geometry: ViewGeometry,
    *,
    voxel_mm: float | None = None,
    shape: tuple[int, int, int] | None = None,
    center_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> VolumeGrid:
    """A grid centred on ``center_mm`` (default the nominal isocenter) covering the views' common field of view."""
    radius, height, _ = fov_radius_height(geometry)
    if voxel_mm is None and shape is None:
        det = geometry.panel
        g = geometry[np.flatnonzero(geometry.valid)]
        mag = float(np.median(g.sdd / g.sod()))
        voxel_mm = float(min(det.pitch_col, det.pitch_row) / mag)
    if shape is None:
        assert voxel_mm is not None
        nxy = int(np.ceil(2 * radius / voxel_mm))
        nz = int(np.ceil(height / voxel_mm))
        shape = (max(nz, 1), max(nxy, 1), max(nxy, 1))
    if voxel_mm is None:
        voxel_mm = float(max(2 * radius / shape[2], 2 * radius / shape[1], height / shape[0]))
    nz, ny, nx = (int(s) for s in shape)
    return VolumeGrid.centered((nz, ny, nx), float(voxel_mm), center_mm)


def check_fov(grid: VolumeGrid, geometry: ViewGeometry, min_fraction: float = 0.05) -> float:
    """Fraction of voxel samples seen by >= 90 % of the views; raises :class:`FieldOfViewError` below ``min_fraction``."""
    z, y, x = grid.coords_mm()
    pick = lambda a: a[np.linspace(0, a.size - 1, min(a.size, 9)).round().astype(int)]  # noqa: E731
    zz, yy, xx = np.meshgrid(pick(z), pick(y), pick(x), indexing="ij")
    pts = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)
    g = geometry[np.flatnonzero(geometry.valid)]
    if g.n_views == 0:
        raise FieldOfViewError("the geometry has no valid (finite) views")
    uv, w = g.project_with_depth(pts)
    det = g.panel
    inside = (
        (w > 0)
        & (uv[..., 0] > -0.5)
        & (uv[..., 0] < det.cols - 0.5)
        & (uv[..., 1] > -0.5)
        & (uv[..., 1] < det.rows - 0.5)
    )
    frac = float((inside.mean(axis=0) >= 0.9).mean())  # samples seen by at least 90 % of the views
    if frac < min_fraction:
        ext = grid.extent_mm
        raise FieldOfViewError(
            f"the volume grid (x {ext[0, 0]:.1f}..{ext[0, 1]:.1f}, y {ext[1, 0]:.1f}..{ext[1, 1]:.1f}, "
            f"z {ext[2, 0]:.1f}..{ext[2, 1]:.1f} mm) misses the field of view: only {100 * frac:.1f}% of its "
            f"samples are seen by 90% of the views (need >= {100 * min_fraction:.0f}%); move or shrink the grid"
        )
    return frac
