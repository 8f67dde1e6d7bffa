"""FDK for any per-view geometry: cosine weights, windowed ramp filter, redundancy weights, voxel back-projection."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import scipy.fft
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry, VolumeGrid
from orbitct.progress import ProgressCallback, report
from recon.errors import ReconError
from recon.grid import views_isocenter
from recon.operator import backproject_padded

WINDOWS = ("ram-lak", "shepp-logan", "cosine", "hann")


class ProjectionStack(Protocol):
    """Anything sliceable along views that yields float32 ``(k, rows, cols)`` line integrals."""

    @property
    def shape(self) -> tuple[int, ...]:
        """``(views, rows, cols)``."""

    def __getitem__(self, index: slice | NDArray[np.intp]) -> NDArray[np.float32]: ...


def ramp_filter(n_cols: int, window: str = "ram-lak") -> NDArray[np.float64]:
    """Frequency response (rfft of length ``2 * n_cols`` padded) of the discrete ramp, 1-pixel spacing."""
    if window not in WINDOWS:
        raise ReconError(f"unknown filter window {window!r}; choose one of {WINDOWS}")
    npad = scipy.fft.next_fast_len(2 * n_cols)
    n = np.arange(npad)
    n = np.where(n > npad // 2, n - npad, n)
    h = np.zeros(npad)
    h[0] = 0.25
    odd = n % 2 == 1
    h[odd] = -1.0 / (np.pi * n[odd]) ** 2
    H = np.real(scipy.fft.rfft(h))
    f = np.arange(H.size) / (npad / 2)  # 0 .. 1 (Nyquist)
    if window == "shepp-logan":
        H *= np.sinc(f / 2)
    elif window == "cosine":
        H *= np.cos(np.pi * f / 2)
    elif window == "hann":
        H *= 0.5 * (1 + np.cos(np.pi * f))
    return H


def fan_angles(geometry: ViewGeometry, center: NDArray[np.float64]) -> NDArray[np.float64]:
    """Signed in-plane (xy) fan angle of every detector column, per view ``(N, cols)``."""
    det = geometry.panel
    c0, _ = det.center
    cols = np.arange(det.cols) - c0
    central = center[None, :2] - geometry.S[:, :2]
    ray = (geometry.D - geometry.S)[:, None, :2] + cols[None, :, None] * geometry.u[:, None, :2]
    cross = central[:, None, 0] * ray[..., 1] - central[:, None, 1] * ray[..., 0]
    dot = central[:, None, 0] * ray[..., 0] + central[:, None, 1] * ray[..., 1]
    return np.arctan2(cross, dot)


def redundancy_weights(
    geometry: ViewGeometry, short_scan: str = "auto"
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, str]:
    """Per-view angular weights, optional Parker weights per (view, column), and the scheme used.

    Views are weighted by their azimuth increment about the rotation axis so that the
    weights sum to pi (full or multiple turns); a single arc shorter than a turn but at least
    pi plus the fan gets Parker weights (``short_scan`` 'auto' | 'parker' | 'none').
    """
    if short_scan not in ("auto", "parker", "none"):
        raise ReconError(f"short_scan must be 'auto', 'parker' or 'none', got {short_scan!r}")
    center = views_isocenter(geometry)
    az = np.unwrap(np.arctan2(geometry.S[:, 1] - center[1], geometry.S[:, 0] - center[0]))
    n = az.size
    if n == 1:
        return np.array([np.pi]), None, "single view"
    sign = 1.0 if az[-1] >= az[0] else -1.0
    beta = sign * (az - az[0])
    dbeta = np.abs(np.gradient(beta))
    med = float(np.median(dbeta)) if np.any(dbeta > 0) else 1.0
    dbeta = np.clip(dbeta, 0.0, 5 * med)
    total = float(dbeta.sum())
    gamma = sign * fan_angles(geometry, center)
    delta = float(np.max(np.abs(gamma)))
    coverage = float(beta.max() - beta.min())
    monotone = bool(np.all(np.diff(beta) >= -1e-9))
    if total <= 0:
        raise ReconError("the views do not rotate about the z axis; FDK needs an azimuthal sweep")
    short = monotone and coverage < 2 * np.pi - 2 * med
    if short_scan == "none" or not short or (short_scan == "auto" and coverage < np.pi + delta):
        return dbeta * np.pi / total, None, "azimuth increments"
    d = max((coverage - np.pi) / 2, 1e-6)
    b = (beta - beta.min())[:, None]
    g = np.clip(gamma, -d + 1e-9, d - 1e-9)
    w = np.ones_like(g)
    r1 = b < 2 * (d - g)
    w = np.where(r1, np.sin(np.pi / 4 * b / (d - g)) ** 2, w)
    r3 = b > np.pi - 2 * g
    w = np.where(r3, np.sin(np.pi / 4 * np.clip(np.pi + 2 * d - b, 0, None) / (d + g)) ** 2, w)
    return dbeta, w, "parker"


def filter_coefficients(geometry: ViewGeometry) -> NDArray[np.float64]:
    """Per view ``(N, 10)``: what the cosine weight and the filter's scale need, ``|pixel - source|^2`` as a quadratic
    form in (col - c0, row - r0) (``d.d, d.u, d.v, u.u, v.v, u.v`` with ``d`` = panel centre - source), then ``c0``,
    ``r0``, the source-detector distance and one over the column spacing on the isocenter plane."""
    det = geometry.panel
    c0, r0 = det.center
    d = geometry.D - geometry.S
    u, v = geometry.u, geometry.v
    tau = det.pitch_col * geometry.sod() / geometry.sdd

    def dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.einsum("ij,ij->i", a, b)

    n = geometry.n_views
    return np.stack(
        [dot(d, d), dot(d, u), dot(d, v), dot(u, u), dot(v, v), dot(u, v), np.full(n, c0), np.full(n, r0)]
        + [geometry.sdd, 1.0 / tau],
        axis=1,
    )


def filter_views(
    proj: NDArray[np.float32],
    geometry: ViewGeometry,
    H: NDArray[np.float64],
    parker: NDArray[np.float64] | None,
    out: NDArray[np.float32],
) -> None:
    """Cosine-weight and ramp-filter ``proj`` row by row into the interior of the padded ``out``."""
    det = geometry.panel
    npad = 2 * (H.size - 1)
    Hf = H.astype(np.float32)
    for n, (dd, du, dv, uu, vv, uv, c0, r0, sdd, inv_tau) in enumerate(filter_coefficients(geometry)):
        cc = np.arange(det.cols) - c0
        rr = np.arange(det.rows) - r0
        # |pixel - source|^2 is a quadratic form in (col, row): no (rows, cols, 3) temporaries
        dist2 = (
            dd
            + 2 * du * cc[None, :]
            + 2 * dv * rr[:, None]
            + uu * cc[None, :] ** 2
            + vv * rr[:, None] ** 2
            + 2 * uv * cc[None, :] * rr[:, None]
        )
        g = np.asarray(proj[n], dtype=np.float32) * (sdd / np.sqrt(dist2)).astype(np.float32)
        if parker is not None:
            g *= parker[n][None, :].astype(np.float32)
        spec = scipy.fft.rfft(g, n=npad, axis=-1)
        spec *= Hf
        out[n, 1:-1, 1:-1] = scipy.fft.irfft(spec, n=npad, axis=-1)[:, : det.cols] * np.float32(inv_tau)


@dataclass(frozen=True)
class FdkWeights:
    """What FDK weights each view by, fixed by the whole orbit: the ramp filter, per-view weights (angular increment
    times SOD^2) and optional Parker weights per (view, column). A part of the views is back-projected with its
    rows of these (:func:`fdk_views`), so parts computed apart sum to the whole."""

    H: NDArray[np.float64]
    weights: NDArray[np.float64]
    parker: NDArray[np.float64] | None

    @classmethod
    def of(cls, geometry: ViewGeometry, window: str = "ram-lak", short_scan: str = "auto") -> FdkWeights:
        """The weights of every view of ``geometry``."""
        if not geometry.valid.all():
            raise ReconError("FDK needs finite geometry for every view it is given")
        wv, parker, _ = redundancy_weights(geometry, short_scan)
        return cls(ramp_filter(geometry.panel.cols, window), wv * geometry.sod() ** 2, parker)

    @property
    def taps(self) -> NDArray[np.float32]:
        """The ramp filter's impulse response, circular over the padded FFT length (a direct convolution with it,
        as the GPU filters, equals the FFT filtering of :func:`filter_views`)."""
        return scipy.fft.irfft(self.H, n=2 * (self.H.size - 1)).astype(np.float32)

    def part(self, views: slice | NDArray[np.intp]) -> FdkWeights:
        """The weights of some of the views."""
        return FdkWeights(self.H, self.weights[views], None if self.parker is None else self.parker[views])


def fdk(
    projections: NDArray[np.float32] | ProjectionStack,
    grid: VolumeGrid,
    geometry: ViewGeometry,
    *,
    window: str = "ram-lak",
    short_scan: str = "auto",
    chunk: int = 8,
    out: NDArray[np.float32] | None = None,
    progress: ProgressCallback | None = None,
    device: str = "cpu",
) -> NDArray[np.float32]:
    """FDK volume (1/mm) from line integrals ``(views, rows, cols)`` of ``geometry`` (exact for circles).

    ``out`` (float32, the grid's shape, may be a view such as a padded volume's interior)
    receives the volume instead of a new array. ``device``: where filtering and back-projection run, ``cpu`` or
    ``cuda`` (:mod:`recon.device`).
    """
    det = geometry.panel
    n = geometry.n_views
    if tuple(projections.shape) != (n, det.rows, det.cols):
        raise ReconError(f"projections: expected shape {(n, det.rows, det.cols)}, got {tuple(projections.shape)}")
    return fdk_views(
        projections,
        grid,
        geometry,
        FdkWeights.of(geometry, window, short_scan),
        chunk=chunk,
        out=out,
        progress=progress,
        device=device,
    )


def fdk_views(
    projections: NDArray[np.float32] | ProjectionStack,
    grid: VolumeGrid,
    geometry: ViewGeometry,
    weights: FdkWeights,
    *,
    chunk: int = 8,
    out: NDArray[np.float32] | None = None,
    progress: ProgressCallback | None = None,
    device: str = "cpu",
) -> NDArray[np.float32]:
    """The back-projection of some views (their ``geometry``, ``weights`` and line integrals); FDK is its sum
    over all views."""
    det = geometry.panel
    n = geometry.n_views
    if out is None:
        vol = np.zeros(grid.shape, dtype=np.float32)
    elif out.shape != grid.shape or out.dtype != np.float32:
        raise ReconError(f"out: expected float32 {grid.shape}, got {out.dtype} {out.shape}")
    else:
        vol = out
        vol[...] = 0.0
    if device == "cuda":
        return _fdk_views_on_gpu(projections, grid, geometry, weights, max(chunk, 32), vol, progress)
    buf = np.zeros((min(chunk, n), det.rows + 2, det.cols + 2), dtype=np.float32)
    for i0 in range(0, n, chunk):
        i1 = min(n, i0 + chunk)
        g = geometry[i0:i1]
        part = buf[: i1 - i0]
        filter_views(projections[i0:i1], g, weights.H, None if weights.parker is None else weights.parker[i0:i1], part)
        backproject_padded(part, grid, g, weights.weights[i0:i1], vol)
        report(progress, "fdk", i1, n, "views")
    return vol


def _fdk_views_on_gpu(
    projections: NDArray[np.float32] | ProjectionStack,
    grid: VolumeGrid,
    geometry: ViewGeometry,
    weights: FdkWeights,
    chunk: int,
    vol: NDArray[np.float32],
    progress: ProgressCallback | None,
) -> NDArray[np.float32]:
    """:func:`fdk_views` with filtering and back-projection on the GPU, ``chunk`` views at a time, into ``vol``."""
    from recon.cuda import CudaBackprojector

    on_gpu = CudaBackprojector(grid)
    coefficients = filter_coefficients(geometry)
    taps = weights.taps
    n = geometry.n_views
    for i0 in range(0, n, chunk):
        i1 = min(n, i0 + chunk)
        parker = None if weights.parker is None else weights.parker[i0:i1]
        proj = np.ascontiguousarray(projections[i0:i1], dtype=np.float32)
        on_gpu.add_projections(proj, geometry[i0:i1], coefficients[i0:i1], taps, parker, weights.weights[i0:i1])
        report(progress, "fdk", i1, n, "views")
    return on_gpu.read(vol)
