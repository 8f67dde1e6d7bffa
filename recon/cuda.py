"""Reconstruction operators on one GPU: the projector pair, FDK's back-projection and PWLS's data term.

Host arrays in and out, as on the CPU: :class:`CudaProjector` is a :class:`recon.operator.Projector` whose kernels
run on the device (:mod:`recon.cuda_kernels`). The device keeps the rays, matrices and one volume; projections pass
through it a chunk of views at a time (:data:`CHUNK_BYTES`), so the device memory a reconstruction needs is one
padded volume (three or four for PWLS, :mod:`recon.cuda_pwls`) plus two chunks, whatever the number of views; work
that would not fit is refused before it starts. :func:`peak_bytes` is the most device
memory these arrays held at once since :func:`reset_peak` (one reconstruction at a time per process).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import cuda
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry, VolumeGrid
from recon.cuda_kernels import (
    THREADS,
    adjoint_kernel,
    backproject_kernel,
    blocks,
    fill_kernel,
    filter_kernel,
    forward_kernel,
    residual_kernel,
    scale_kernel,
    strided_blocks,
)
from recon.errors import ReconError
from recon.operator import Projector, index_matrices
from recon.pwls_setup import ordered_subsets, subset_operator, view_rows

CHUNK_BYTES = 256 * 2**20  # projections moved to the device at a time


_peak = [0]


def reset_peak() -> None:
    """Start counting the peak device memory afresh."""
    _peak[0] = 0


def peak_bytes() -> int:
    """The most device memory the arrays of this module held at once since :func:`reset_peak`."""
    return _peak[0]


def _record(held: int) -> None:
    _peak[0] = max(_peak[0], held)


def _check_fits(needed: int, what: str) -> None:
    """Refuse, in one sentence, work whose device arrays would not fit in the device's free memory."""
    free, total = cuda.current_context().get_memory_info()
    if math.isfinite(free) and needed > 0.9 * free:
        raise ReconError(
            f"{what} needs {_size(needed)} of GPU memory and {_size(free)} of {_size(total)} is free; use a larger "
            "voxel size or a smaller shape, or --device cpu"
        )


def _size(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def zeros(n: int) -> Any:
    """A float32 device array of ``n`` zeros."""
    return clear(cuda.device_array(n, np.float32))


def clear(a: Any) -> Any:
    """Set the flat float32 device array ``a`` to zero; returns it."""
    fill_kernel[strided_blocks(a.size), THREADS](a, np.float32(0.0))
    return a


class CudaProjector(Projector):
    """``A = CudaProjector(grid, geometry)``: :class:`~recon.operator.Projector` with its kernels on the GPU."""

    device = "cuda"

    def __init__(self, grid: VolumeGrid, geometry: ViewGeometry, chunk_bytes: int = CHUNK_BYTES) -> None:
        super().__init__(grid, geometry)
        _, rows, cols = self.proj_shape
        self.chunk_views = max(1, min(self.proj_shape[0], chunk_bytes // (4 * rows * cols)))
        self._chunk_setting = chunk_bytes
        self._d_rays = cuda.to_device(self._rays)
        self._d_vox = cuda.to_device(self._vox)
        self.volume_bytes = 4 * math.prod(self.padded_shape)
        self.chunk_bytes = 4 * self.chunk_views * rows * cols
        self.check_fits(1)

    def _held(self, volumes: int, chunks: int) -> None:
        """Record that ``volumes`` padded volumes and ``chunks`` projection chunks are on the device now."""
        _record(self.rays_bytes + volumes * self.volume_bytes + chunks * self.chunk_bytes)

    def check_fits(self, volumes: int, more_bytes: int = 0) -> None:
        """Refuse work that needs ``volumes`` padded volumes, two chunks and ``more_bytes`` when the device has no room
        for them."""
        needed = self.rays_bytes + volumes * self.volume_bytes + 2 * self.chunk_bytes + more_bytes
        nz, ny, nx = self.vol_shape
        _check_fits(needed, f"a {nz} x {ny} x {nx} volume")

    @property
    def rays_bytes(self) -> int:
        """Device memory of the rays."""
        return int(self._rays.nbytes)

    def chunks(self, start: int, stop: int) -> list[tuple[int, int]]:
        """Views ``start..stop`` cut into chunks of at most :attr:`chunk_views`."""
        return [(j, min(j + self.chunk_views, stop)) for j in range(start, stop, self.chunk_views)]

    def forward_on_device(self, d_xp: Any, d_out: Any, start: int, stop: int) -> None:
        """Views ``start..stop`` of the forward projection of the device's padded volume into the flat ``d_out``."""
        nz, ny, nx = self.vol_shape
        _, rows, cols = self.proj_shape
        n = (stop - start) * rows * cols
        forward_kernel[blocks(n), THREADS](d_xp, nx, ny, nz, self._d_rays[start:stop], self._d_vox, rows, cols, d_out)

    def back_on_device(self, d_y: Any, d_acc: Any, start: int, stop: int) -> None:
        """Add the adjoint of views ``start..stop`` (flat ``d_y``) into the device's padded accumulator."""
        nz, ny, nx = self.vol_shape
        _, rows, cols = self.proj_shape
        n = (stop - start) * rows * cols
        adjoint_kernel[blocks(n), THREADS](d_y, nx, ny, nz, self._d_rays[start:stop], self._d_vox, rows, cols, d_acc)

    def forward_padded(
        self, x_padded: NDArray[np.float32], out: NDArray[np.float32], start: int = 0
    ) -> NDArray[np.float32]:
        """Views ``start .. start + len(out)`` of the forward projection of a zero-bordered volume, into ``out``."""
        self._view_rays(start, out, "out")
        d_xp = cuda.to_device(self._checked_padded(x_padded).reshape(-1))
        self._held(1, 1)
        d_out = cuda.device_array(self.chunk_views * math.prod(self.proj_shape[1:]), np.float32)
        for j0, j1 in self.chunks(start, start + out.shape[0]):
            part = out[j0 - start : j1 - start].reshape(-1)
            self.forward_on_device(d_xp, d_out, j0, j1)
            d_out[: part.size].copy_to_host(part)
        return out

    def back_padded(
        self, y: NDArray[np.float32], acc_padded: NDArray[np.float32], start: int = 0
    ) -> NDArray[np.float32]:
        """Add the adjoint of views ``start .. start + len(y)`` into a padded accumulator (its border is scratch)."""
        y = np.ascontiguousarray(y, dtype=np.float32)
        self._view_rays(start, y, "projections")
        acc = self._checked_padded(acc_padded)
        d_acc = zeros(acc.size)
        self._held(1, 1)
        for j0, j1 in self.chunks(start, start + y.shape[0]):
            self.back_on_device(cuda.to_device(y[j0 - start : j1 - start].reshape(-1)), d_acc, j0, j1)
        acc += d_acc.copy_to_host().reshape(acc.shape)
        return acc

    def subset(self, views: NDArray[np.intp]) -> CudaProjector:
        """Operator for a subset of the views."""
        return CudaProjector(self.grid, self.geometry[np.asarray(views)], self._chunk_setting)


class CudaBackprojector:
    """FDK's weighted voxel-driven back-projection into a volume kept on the device, one chunk of views at a time."""

    def __init__(self, grid: VolumeGrid) -> None:
        self.grid = grid
        nz, ny, nx = grid.shape
        _check_fits(4 * nz * ny * nx, f"a {nz} x {ny} x {nx} volume")
        self._vol = zeros(nz * ny * nx)

    def add(self, padded: NDArray[np.float32], geometry: ViewGeometry, weights: NDArray[np.float64]) -> None:
        """Back-project views with a one-pixel zero border ``(k, rows + 2, cols + 2)`` of ``geometry``."""
        d = geometry.panel
        if padded.shape != (geometry.n_views, d.rows + 2, d.cols + 2):
            raise ReconError(f"padded views: expected {(geometry.n_views, d.rows + 2, d.cols + 2)}, got {padded.shape}")
        self._add(cuda.to_device(np.ascontiguousarray(padded, dtype=np.float32).reshape(-1)), geometry, weights)

    def _add(self, img: Any, geometry: ViewGeometry, weights: NDArray[np.float64]) -> None:
        """Back-project the padded views ``img`` (flat, on the device)."""
        d = geometry.panel
        mats = cuda.to_device(index_matrices(self.grid, geometry))
        w = cuda.to_device(np.ascontiguousarray(weights, dtype=np.float64))
        _record(self._vol.size * 4 + img.size * 4 + mats.size * 8 + w.size * 8)
        nz, ny, nx = self.grid.shape
        backproject_kernel[blocks(self._vol.size), THREADS](img, d.rows, d.cols, mats, w, self._vol, nx, ny, nz)

    def add_projections(
        self,
        proj: NDArray[np.float32],
        geometry: ViewGeometry,
        coefficients: NDArray[np.float64],
        taps: NDArray[np.float32],
        parker: NDArray[np.float64] | None,
        weights: NDArray[np.float64],
    ) -> None:
        """Filter line integrals ``(k, rows, cols)`` of ``geometry`` on the device (``recon.fdk.filter_coefficients``,
        the ramp filter's impulse response ``taps``, Parker's weights or None) and back-project them."""
        d = geometry.panel
        k = geometry.n_views
        if proj.shape != (k, d.rows, d.cols):
            raise ReconError(f"projections: expected {(k, d.rows, d.cols)}, got {proj.shape}")
        raw = cuda.to_device(np.ascontiguousarray(proj, dtype=np.float32).reshape(-1))
        padded = zeros(k * (d.rows + 2) * (d.cols + 2))
        use_parker = parker is not None
        p = cuda.to_device(
            np.ascontiguousarray(parker if use_parker else np.ones((1, 1)), dtype=np.float32).reshape(-1)
        )
        d_taps = cuda.to_device(np.ascontiguousarray(taps, dtype=np.float32))
        shared = 4 * (d.cols + taps.size)
        threads = min(THREADS, d.cols)
        filter_kernel[k * d.rows, threads, 0, shared](
            raw, d.rows, d.cols, cuda.to_device(coefficients), p, use_parker, d_taps, padded
        )
        _record(self._vol.size * 4 + raw.size * 4 + padded.size * 4)
        self._add(padded, geometry, weights)

    def read(self, out: NDArray[np.float32]) -> NDArray[np.float32]:
        """Copy the volume into ``out`` (the grid's shape; may be a view such as a padded volume's interior)."""
        out[...] = self._vol.copy_to_host().reshape(self.grid.shape)
        return out


class CudaViewsData:
    """PWLS's data term (:class:`recon.pwls.DataTerm`) on the GPU: per subset, the iterate goes to the device once,
    every chunk of views is projected, compared with its data and back-projected there, and the gradient comes back.

    Projections and weights stay on the device when they fit in ``resident_bytes`` (read once), else they are read
    and moved a chunk at a time every pass (``y`` and ``weights`` may be anything sliceable along views).
    """

    def __init__(
        self,
        A: CudaProjector,
        y: Any,
        weights: Any | None,
        *,
        subsets: int = 1,
        subset_views: list[NDArray[np.intp]] | None = None,
        resident_bytes: int = 8 * 2**30,
    ) -> None:
        self._views = ordered_subsets(A, y, weights, subsets, subset_views)
        self.A, self.y, self.weights = A, y, weights
        self.padded_shape = A.padded_shape
        self.subsets = len(self._views)
        self._ops = [subset_operator(A, v) for v in self._views]
        data_bytes = (2 if weights is not None else 1) * 4 * math.prod(A.proj_shape)
        self._resident = data_bytes <= resident_bytes
        self.resident_bytes = data_bytes if self._resident else 0
        self.check_fits(2)
        self._cache: dict[tuple[int, int, bool], Any] = {}
        self._value = cuda.device_array(1, np.float64)

    def _data(self, m: int, j0: int, j1: int, weights: bool) -> Any:
        """Subset ``m``'s data (or weights) of its chunk ``j0..j1`` on the device."""
        key = (m, j0, weights)
        if key in self._cache:
            return self._cache[key]
        d = cuda.to_device(view_rows(self.weights if weights else self.y, self._views[m][j0:j1]).reshape(-1))
        if self._resident:
            self._cache[key] = d
        return d

    def check_fits(self, volumes: int) -> None:
        """Refuse, before any work, ``volumes`` padded volumes beside the data held on the device when they do not
        fit."""
        self.A.check_fits(volumes, self.resident_bytes + self.A.chunk_bytes)

    def hold(self, volumes: int) -> None:
        """Record that ``volumes`` padded volumes are on the device beside this data term's arrays."""
        held = volumes * self.A.volume_bytes + 3 * self.A.chunk_bytes + self.A.rays_bytes
        _record(held + sum(a.size * 4 for a in self._cache.values()))

    def curvature(self, out: NDArray[np.float32]) -> None:
        """Add ``A^T (w * A 1)`` into the padded ``out``."""
        d_acc = zeros(out.size)
        self.curvature_on_device(d_acc)
        out += d_acc.copy_to_host().reshape(out.shape)

    def curvature_on_device(self, d_acc: Any) -> None:
        """Add ``A^T (w * A 1)`` into the padded flat device array ``d_acc``."""
        ones = np.zeros(self.padded_shape, np.float32)
        ones[1:-1, 1:-1, 1:-1] = 1.0
        d_ones = cuda.to_device(ones.reshape(-1))
        d_r = cuda.device_array(self.A.chunk_views * math.prod(self.A.proj_shape[1:]), np.float32)
        whole = np.arange(self.A.proj_shape[0])
        for j0, j1 in self.A.chunks(0, whole.size):
            r = d_r[: (j1 - j0) * math.prod(self.A.proj_shape[1:])]
            self.A.forward_on_device(d_ones, r, j0, j1)
            if self.weights is not None:
                scale_kernel[strided_blocks(r.size), THREADS](
                    r, cuda.to_device(view_rows(self.weights, whole[j0:j1]).reshape(-1))
                )
            self.A.back_on_device(r, d_acc, j0, j1)
        self.hold(2)

    def gradient(self, xp: NDArray[np.float32], subset: int, out: NDArray[np.float32] | None) -> float:
        """Subset ``subset``'s data term at ``xp``; its gradient added into ``out`` unless None."""
        d_acc = zeros(xp.size) if out is not None else None
        value = self.gradient_on_device(cuda.to_device(np.ascontiguousarray(xp).reshape(-1)), subset, d_acc)
        if out is not None and d_acc is not None:
            out += d_acc.copy_to_host().reshape(out.shape)
        return value

    def gradient_on_device(self, d_xp: Any, subset: int, d_acc: Any | None) -> float:
        """:meth:`gradient` with the padded volumes flat on the device (``d_acc`` None: the value only)."""
        op = self._ops[subset]
        if op is None:  # an empty subset
            return 0.0
        per_view = math.prod(op.proj_shape[1:])
        d_r = cuda.device_array(op.chunk_views * per_view, np.float32)
        self._value.copy_to_device(np.zeros(1))
        weighted = self.weights is not None
        for j0, j1 in op.chunks(0, op.proj_shape[0]):
            r = d_r[: (j1 - j0) * per_view]
            op.forward_on_device(d_xp, r, j0, j1)
            w = self._data(subset, j0, j1, True) if weighted else r
            residual_kernel[strided_blocks(r.size), THREADS](
                r, self._data(subset, j0, j1, False), w, weighted, self._value
            )
            if d_acc is not None:
                op.back_on_device(r, d_acc, j0, j1)
        self.hold(2 if d_acc is not None else 1)
        return float(self._value.copy_to_host()[0])
