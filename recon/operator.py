"""Linear projection operator ``A`` for a volume grid and any per-view geometry."""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry
from recon.errors import ReconError
from recon.grid import VolumeGrid
from recon.projector import add_interiors, joseph_adjoint, joseph_forward, voxel_backproject


def index_rays(grid: VolumeGrid, geometry: ViewGeometry) -> NDArray[np.float64]:
    """Per-view ``(N, 12)`` rays in voxel-index units: source, pixel (0,0), column step, row step."""
    vox = np.asarray(grid.voxel_mm)
    org = np.asarray(grid.origin_mm)
    c0, r0 = geometry.detector.center
    p00 = geometry.D - c0 * geometry.u - r0 * geometry.v
    return np.ascontiguousarray(
        np.concatenate([(geometry.S - org) / vox, (p00 - org) / vox, geometry.u / vox, geometry.v / vox], axis=1)
    )


def index_matrices(grid: VolumeGrid, geometry: ViewGeometry) -> NDArray[np.float64]:
    """Projection matrices acting on voxel indices ``(x, y, z, 1)``; ``w`` stays depth in mm."""
    T = np.diag(list(grid.voxel_mm) + [1.0])
    T[:3, 3] = grid.origin_mm
    return np.ascontiguousarray(geometry.matrices @ T)


def pad_volume(x: NDArray[np.float32], out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """``x`` with a one-voxel zero border (written into ``out`` when given)."""
    nz, ny, nx = x.shape
    if out is None:
        out = np.empty((nz + 2, ny + 2, nx + 2), dtype=np.float32)
    out[0] = 0.0
    out[-1] = 0.0
    out[:, 0] = 0.0
    out[:, -1] = 0.0
    out[:, :, 0] = 0.0
    out[:, :, -1] = 0.0
    out[1:-1, 1:-1, 1:-1] = x
    return out


class Projector:
    """``A = Projector(grid, geometry)``: ``A(x)`` forward-projects, ``A.T(y)`` is its exact adjoint.

    Keeps padded scratch buffers between calls: use one instance from one thread at a time.
    """

    def __init__(self, grid: VolumeGrid, geometry: ViewGeometry) -> None:
        if geometry.n_views == 0:
            raise ReconError("the geometry has no views to project onto")
        if not geometry.valid.all():
            bad = np.flatnonzero(~geometry.valid)[:5].tolist()
            raise ReconError(f"the geometry has non-finite views {bad}; pass only projection views")
        self.grid = grid
        self.geometry = geometry
        self._rays = index_rays(grid, geometry)
        self._vox = np.asarray(grid.voxel_mm, dtype=np.float64)
        self._buf: NDArray[np.float32] | None = None

    @property
    def vol_shape(self) -> tuple[int, int, int]:
        """Volume shape (nz, ny, nx)."""
        return self.grid.shape

    @property
    def proj_shape(self) -> tuple[int, int, int]:
        """Projection stack shape (views, rows, cols)."""
        d = self.geometry.detector
        return (self.geometry.n_views, d.rows, d.cols)

    def forward(self, x: NDArray[np.float32], out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
        """Line integrals (mm x 1/mm) of volume ``x`` for every pixel of every view."""
        x = _as_f32(x, self.vol_shape, "volume")
        if out is None:
            out = np.empty(self.proj_shape, dtype=np.float32)
        # the padded copy lives in the first adjoint accumulator: the two are never needed at once
        joseph_forward(pad_volume(x, self._scratch()[0]), self._rays, self._vox, out)
        return out

    def back(self, y: NDArray[np.float32], out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
        """Matched back-projection ``A^T y`` (added to ``out`` when given)."""
        y = _as_f32(y, self.proj_shape, "projections")
        if out is None:
            out = np.zeros(self.vol_shape, dtype=np.float32)
        acc = self._scratch()
        acc.fill(0.0)
        joseph_adjoint(y, self._rays, self._vox, acc)
        add_interiors(acc, out)
        return out

    def _scratch(self) -> NDArray[np.float32]:
        """Padded per-task buffers ``(threads, nz + 2, ny + 2, nx + 2)``, kept between calls."""
        nz, ny, nx = self.vol_shape
        shape = (numba.get_num_threads(), nz + 2, ny + 2, nx + 2)
        if self._buf is None or self._buf.shape != shape:
            self._buf = None
            self._buf = np.empty(shape, dtype=np.float32)
        return self._buf

    def release(self) -> None:
        """Free the scratch buffers kept between calls."""
        self._buf = None

    __call__ = forward

    @property
    def T(self) -> "_Adjoint":
        """The adjoint operator."""
        return _Adjoint(self)

    def subset(self, views: NDArray[np.intp]) -> "Projector":
        """Operator for a subset of the views."""
        return Projector(self.grid, self.geometry[np.asarray(views)])


class _Adjoint:
    def __init__(self, a: Projector) -> None:
        self._a = a

    def __call__(self, y: NDArray[np.float32]) -> NDArray[np.float32]:
        return self._a.back(y)

    @property
    def T(self) -> Projector:
        return self._a


def projector(grid: VolumeGrid, geometry: ViewGeometry) -> Projector:
    """The projection operator of ``grid`` seen by ``geometry``."""
    return Projector(grid, geometry)


def backproject_voxels(proj: NDArray[np.float32], grid: VolumeGrid, geometry: ViewGeometry,
                       weights: NDArray[np.float64], out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """Voxel-driven back-projection with per-view ``weights`` divided by depth squared (FDK)."""
    d = geometry.detector
    proj = _as_f32(proj, (geometry.n_views, d.rows, d.cols), "projections")
    if out is None:
        out = np.zeros(grid.shape, dtype=np.float32)
    padded = np.zeros((proj.shape[0], d.rows + 2, d.cols + 2), dtype=np.float32)
    padded[:, 1:-1, 1:-1] = proj
    return backproject_padded(padded, grid, geometry, weights, out)


def backproject_padded(padded: NDArray[np.float32], grid: VolumeGrid, geometry: ViewGeometry,
                       weights: NDArray[np.float64], out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """:func:`backproject_voxels` for projections that already carry a one-pixel zero border."""
    if out is None:
        out = np.zeros(grid.shape, dtype=np.float32)
    voxel_backproject(padded, index_matrices(grid, geometry), np.ascontiguousarray(weights, dtype=np.float64), out)
    return out


def _as_f32(a: NDArray, shape: tuple[int, ...], what: str) -> NDArray[np.float32]:
    a = np.ascontiguousarray(a, dtype=np.float32)
    if a.shape != tuple(shape):
        raise ReconError(f"{what}: expected shape {tuple(shape)}, got {a.shape}")
    return a
