"""Linear projection operator ``A`` for a volume grid and any per-view geometry."""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry, VolumeGrid
from recon.errors import ReconError
from recon.projector import (
    MAX_PADDED_VOXELS,
    joseph_adjoint,
    joseph_forward,
    ray_slab_range,
    slab_bounds,
    voxel_backproject,
)


def index_rays(grid: VolumeGrid, geometry: ViewGeometry) -> NDArray[np.float64]:
    """Per-view ``(N, 12)`` rays in voxel-index units: source, pixel (0,0), column step, row step."""
    vox = np.asarray(grid.voxel_mm)
    org = np.asarray(grid.origin_mm)
    c0, r0 = geometry.panel.center
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

    Keeps one padded scratch volume between calls: use one instance from one thread at a time.
    :meth:`forward_padded` and :meth:`back_padded` work on padded volumes and on any range of
    views, for callers that stream projections in chunks and keep their own padded buffers.
    """

    device = "cpu"  # where its kernels run (recon.cuda.CudaProjector: "cuda")

    def __init__(self, grid: VolumeGrid, geometry: ViewGeometry) -> None:
        if geometry.n_views == 0:
            raise ReconError("the geometry has no views to project onto")
        if not geometry.valid.all():
            bad = np.flatnonzero(~geometry.valid)[:5].tolist()
            raise ReconError(f"the geometry has non-finite views {bad}; pass only projection views")
        nz, ny, nx = grid.shape
        if self.device == "cpu" and (nz + 2) * (ny + 2) * (nx + 2) > MAX_PADDED_VOXELS:
            raise ReconError(
                f"the {nx} x {ny} x {nz} volume is too large for the CPU projector (at most {MAX_PADDED_VOXELS:.3g} "
                "voxels with a one-voxel border); use larger voxels or a smaller grid"
            )
        self.grid = grid
        self.geometry = geometry
        self._rays = index_rays(grid, geometry)
        self._vox = np.asarray(grid.voxel_mm, dtype=np.float64)
        self._buf: NDArray[np.float32] | None = None
        self._slab_tables: dict[tuple[int, int], tuple[NDArray[np.int64], NDArray[np.int64]]] = {}

    @property
    def vol_shape(self) -> tuple[int, int, int]:
        """Volume shape (nz, ny, nx)."""
        return self.grid.shape

    @property
    def padded_shape(self) -> tuple[int, int, int]:
        """Shape of the zero-bordered volumes of :meth:`forward_padded` and :meth:`back_padded`."""
        nz, ny, nx = self.vol_shape
        return (nz + 2, ny + 2, nx + 2)

    @property
    def proj_shape(self) -> tuple[int, int, int]:
        """Projection stack shape (views, rows, cols)."""
        d = self.geometry.panel
        return (self.geometry.n_views, d.rows, d.cols)

    def forward(self, x: NDArray[np.float32], out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
        """Line integrals (mm x 1/mm) of volume ``x`` for every pixel of every view."""
        x = _as_f32(x, self.vol_shape, "volume")
        if out is None:
            out = np.empty(self.proj_shape, dtype=np.float32)
        return self.forward_padded(pad_volume(x, self._scratch()), out)

    def back(self, y: NDArray[np.float32], out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
        """Matched back-projection ``A^T y`` (added to ``out`` when given)."""
        y = _as_f32(y, self.proj_shape, "projections")
        if out is None:
            out = np.zeros(self.vol_shape, dtype=np.float32)
        acc = self._scratch()
        acc.fill(0.0)
        self.back_padded(y, acc)
        out += acc[1:-1, 1:-1, 1:-1]
        return out

    def forward_padded(
        self, x_padded: NDArray[np.float32], out: NDArray[np.float32], start: int = 0
    ) -> NDArray[np.float32]:
        """Views ``start .. start + len(out)`` of the forward projection of a zero-bordered volume, into ``out``."""
        rays = self._view_rays(start, out, "out")
        joseph_forward(self._checked_padded(x_padded), rays, self._vox, out)
        return out

    def back_padded(
        self, y: NDArray[np.float32], acc_padded: NDArray[np.float32], start: int = 0
    ) -> NDArray[np.float32]:
        """Add the adjoint of views ``start .. start + len(y)`` into a padded accumulator (its border is scratch)."""
        y = np.ascontiguousarray(y, dtype=np.float32)
        rays = self._view_rays(start, y, "projections")
        acc = self._checked_padded(acc_padded)
        nz = self.vol_shape[0]
        lo, hi = self._slab_table(start, start + y.shape[0])
        # one slab per thread and parity: every extra slab repeats the set-up of the rays that cross it
        # (measured: 16 slabs on 2 threads cost 15 % more than 4)
        joseph_adjoint(y, rays, self._vox, acc, slab_bounds(nz, 2 * numba.get_num_threads()), lo, hi)
        return acc

    def check_stacks(self, **stacks: Any) -> None:
        """Refuse, naming it, a stack (projections, weights; None: absent) not of this operator's projection shape."""
        for what, stack in stacks.items():
            if stack is not None and tuple(stack.shape) != self.proj_shape:
                raise ReconError(f"{what}: expected shape {self.proj_shape}, got {tuple(stack.shape)}")

    def _slab_table(self, start: int, stop: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """z extent (slab coordinates) of every (view, row) line of views ``start..stop``, kept per chunk."""
        key = (start, stop)
        if key not in self._slab_tables:
            nz, ny, nx = self.vol_shape
            _, rows, cols = self.proj_shape
            lo = np.empty((stop - start) * rows, np.int64)
            hi = np.empty_like(lo)
            ray_slab_range(self._rays[start:stop], self._vox, nz, ny, nx, rows, cols, lo, hi)
            self._slab_tables[key] = (lo, hi)
        return self._slab_tables[key]

    def _checked_padded(self, a: NDArray[np.float32]) -> NDArray[np.float32]:
        """``a`` if it is a C-contiguous float32 padded volume of this grid, else a ReconError."""
        shape = self.padded_shape
        if a.shape != shape or a.dtype != np.float32 or not a.flags.c_contiguous:
            raise ReconError(f"padded volume: expected C-contiguous float32 {shape}, got {a.dtype} {a.shape}")
        return a

    def _view_rays(self, start: int, arr: NDArray[np.float32], what: str) -> NDArray[np.float64]:
        _, rows, cols = self.proj_shape
        stop = start + arr.shape[0]
        if arr.ndim != 3 or arr.shape[1:] != (rows, cols) or arr.dtype != np.float32 or not arr.flags.c_contiguous:
            raise ReconError(f"{what}: expected C-contiguous float32 (k, {rows}, {cols}), got {arr.dtype} {arr.shape}")
        if not 0 <= start <= stop <= self.proj_shape[0]:
            raise ReconError(f"{what}: views {start}..{stop} outside 0..{self.proj_shape[0]}")
        return self._rays[start:stop]

    def _scratch(self) -> NDArray[np.float32]:
        """One padded volume, kept between calls (the padded input of forward, the accumulator of back)."""
        if self._buf is None:
            self._buf = np.empty(self.padded_shape, dtype=np.float32)
        return self._buf

    def release(self) -> None:
        """Free the scratch volume and the per-chunk tables kept between calls."""
        self._buf = None
        self._slab_tables.clear()

    __call__ = forward

    @property
    def T(self) -> _Adjoint:
        """The adjoint operator."""
        return _Adjoint(self)

    def subset(self, views: NDArray[np.intp]) -> Projector:
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


def backproject_voxels(
    proj: NDArray[np.float32],
    grid: VolumeGrid,
    geometry: ViewGeometry,
    weights: NDArray[np.float64],
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """Voxel-driven back-projection with per-view ``weights`` divided by depth squared (FDK)."""
    d = geometry.panel
    proj = _as_f32(proj, (geometry.n_views, d.rows, d.cols), "projections")
    if out is None:
        out = np.zeros(grid.shape, dtype=np.float32)
    padded = np.zeros((proj.shape[0], d.rows + 2, d.cols + 2), dtype=np.float32)
    padded[:, 1:-1, 1:-1] = proj
    return backproject_padded(padded, grid, geometry, weights, out)


def backproject_padded(
    padded: NDArray[np.float32],
    grid: VolumeGrid,
    geometry: ViewGeometry,
    weights: NDArray[np.float64],
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """:func:`backproject_voxels` for projections that already carry a one-pixel zero border."""
    if out is None:
        out = np.zeros(grid.shape, dtype=np.float32)
    voxel_backproject(padded, index_matrices(grid, geometry), np.ascontiguousarray(weights, dtype=np.float64), out)
    return out


def _as_f32(a: NDArray[Any], shape: tuple[int, ...], what: str) -> NDArray[np.float32]:
    a = np.ascontiguousarray(a, dtype=np.float32)
    if a.shape != tuple(shape):
        raise ReconError(f"{what}: expected shape {tuple(shape)}, got {a.shape}")
    return a
