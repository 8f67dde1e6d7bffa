"""Exact line-integral images of analytic phantoms: per-primitive detector footprints, numba kernel."""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import GeometryError, ViewGeometry
from orbitct.phantoms.chords import chord_dt
from orbitct.phantoms.phantom import Phantom
from orbitct.progress import ProgressCallback, report
from orbitct.simulator.beam import Beam


@nb.njit(parallel=True, cache=True, nogil=True)
def _render(
    out: NDArray[np.float32],
    kind: NDArray[np.int64],
    a: NDArray[np.float64],
    b00: NDArray[np.float64],
    bu: NDArray[np.float64],
    bv: NDArray[np.float64],
    mu: NDArray[np.float64],
    fp: NDArray[np.int64],
    ss: NDArray[np.int64],
    d00: NDArray[np.float64],
    du: NDArray[np.float64],
    dv: NDArray[np.float64],
) -> None:
    rows = out.shape[0]
    K = kind.shape[0]
    for i in nb.prange(rows):
        for k in range(K):
            if i < fp[k, 0] or i > fp[k, 1]:
                continue
            n = ss[k]
            kk = kind[k]
            a0, a1, a2 = a[k, 0], a[k, 1], a[k, 2]
            for j in range(fp[k, 2], fp[k, 3] + 1):
                acc = 0.0
                for qi in range(n):
                    fi = i + (qi + 0.5) / n - 0.5
                    for qj in range(n):
                        fj = j + (qj + 0.5) / n - 0.5
                        b0 = b00[k, 0] + fj * bu[k, 0] + fi * bv[k, 0]
                        b1 = b00[k, 1] + fj * bu[k, 1] + fi * bv[k, 1]
                        b2 = b00[k, 2] + fj * bu[k, 2] + fi * bv[k, 2]
                        dt = chord_dt(kk, a0, a1, a2, b0, b1, b2)
                        if dt > 0.0:
                            x = d00[0] + fj * du[0] + fi * dv[0]
                            y = d00[1] + fj * du[1] + fi * dv[1]
                            z = d00[2] + fj * du[2] + fi * dv[2]
                            acc += dt * np.sqrt(x * x + y * y + z * z)
                if acc > 0.0:
                    out[i, j] += mu[k] * acc / (n * n)


@nb.njit(cache=True, nogil=True)
def _deposit_segment(
    out: NDArray[np.float32],
    p0: NDArray[np.float64],
    p1: NDArray[np.float64],
    n: int,
    P: NDArray[np.float64],
    S: NDArray[np.float64],
    P00: NDArray[np.float64],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    sdd: float,
    mass_per_mm: float,
    pixel_area: float,
    radius: float,
    pitch: float,
) -> None:
    """Pixel-averaged line integrals of a thin wire: its mass per mm spread along ``p0 -> p1`` onto the pixels."""
    rows, cols = out.shape
    step = np.sqrt(((p1 - p0) ** 2).sum()) / n
    for k in range(n):
        f = (k + 0.5) / n
        x0 = p0[0] + f * (p1[0] - p0[0])
        x1 = p0[1] + f * (p1[1] - p0[1])
        x2 = p0[2] + f * (p1[2] - p0[2])
        w = P[2, 0] * x0 + P[2, 1] * x1 + P[2, 2] * x2 + P[2, 3]
        if w <= 0.0:
            continue
        col = (P[0, 0] * x0 + P[0, 1] * x1 + P[0, 2] * x2 + P[0, 3]) / w
        row = (P[1, 0] * x0 + P[1, 1] * x1 + P[1, 2] * x2 + P[1, 3]) / w
        # detector area per unit area across the ray: (|p - S| / |x - S|)^2 / cos(obliquity)
        h = P00 + col * u + row * v - S
        dist = np.sqrt((h**2).sum())
        m = mass_per_mm * step * (sdd / w) ** 2 * dist / sdd / pixel_area
        # spread over the wire's projected width (a box), shared by the pixels it overlaps
        hw = max(radius * sdd / w / pitch, 1e-6)
        for ir in range(int(np.floor(row - hw + 0.5)), int(np.floor(row + hw + 0.5)) + 1):
            if ir < 0 or ir >= rows:
                continue
            fr = (min(row + hw, ir + 0.5) - max(row - hw, ir - 0.5)) / (2 * hw)
            for ic in range(int(np.floor(col - hw + 0.5)), int(np.floor(col + hw + 0.5)) + 1):
                if ic < 0 or ic >= cols:
                    continue
                fc = (min(col + hw, ic + 0.5) - max(col - hw, ic - 0.5)) / (2 * hw)
                if fr > 0 and fc > 0:
                    out[ir, ic] += m * fr * fc


def _supersampling(size_px: NDArray[np.float64], supersample: bool | int) -> NDArray[np.int64]:
    if supersample is False or supersample is None:
        return np.ones(size_px.shape, np.int64)
    if supersample is True:
        return np.where(size_px >= 16, 1, np.where(size_px >= 4, 3, 5)).astype(np.int64)
    if int(supersample) < 1:
        raise ValueError(f"supersample must be True, False or an integer >= 1, got {supersample!r}")
    return np.full(size_px.shape, int(supersample), np.int64)


def line_integrals(
    phantom: Phantom,
    geometry: ViewGeometry,
    index: int = 0,
    *,
    supersample: bool | int = True,
    beam: Beam | None = None,
) -> NDArray[np.float32]:
    """Line-integral image ``(rows, cols)`` float32 of view ``index``: exact chords through every primitive.

    ``supersample=True`` averages 3x3 or 5x5 rays per pixel over primitives smaller than 16 or
    4 pixels on the detector (BBs), and projects cylinders thinner than half a pixel (wires) by
    their mass per unit length (pixel averages); ``False`` uses the pixel-centre ray only; an
    integer ``n`` uses ``n x n`` rays for every primitive. With a polychromatic ``beam``, each
    material is projected apart and the image is what the panel reads, ``-ln(I / I0)``, beam
    hardening included; without, the attenuations hold at one energy.
    """
    if not 0 <= index < geometry.n_views and not -geometry.n_views <= index < 0:
        raise GeometryError(f"view index {index} out of range for {geometry.n_views} views")
    if beam is not None:
        parts = phantom.by_material
        return beam.harden({k: line_integrals(p, geometry, index, supersample=supersample) for k, p in parts.items()})
    det = geometry.panel
    vec = geometry.vectors[index]
    if not np.isfinite(vec).all():
        raise GeometryError(f"view {index} has non-finite geometry (not a projection frame?)")
    S, D, u, v = vec[0:3], vec[3:6], vec[6:9], vec[9:12]
    c0, r0 = det.center
    P00 = D - c0 * u - r0 * v
    pk = phantom.packed
    R, c, s = pk.rotation, pk.center, pk.semi_axes
    # local (unit-shape) coordinates: y = R^T (x - c) / s
    a = np.einsum("kji,kj->ki", R, S[None] - c) / s
    b00 = np.einsum("kji,j->ki", R, P00 - S) / s
    bu = np.einsum("kji,j->ki", R, u) / s
    bv = np.einsum("kji,j->ki", R, v) / s
    # footprints from the projected bounding-box corners
    P = geometry.matrices[index]
    h = np.einsum("ij,kcj->kci", P[:, :3], pk.corners) + P[:, 3]
    depth = h[..., 2]
    out = np.zeros(det.shape, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        col = h[..., 0] / depth
        row = h[..., 1] / depth
    behind = (depth <= 1e-6).any(axis=1)
    fp = np.empty((len(pk.kind), 4), dtype=np.int64)
    rmin = np.floor(np.nan_to_num(row.min(1), nan=0.0)) - 1
    rmax = np.ceil(np.nan_to_num(row.max(1), nan=0.0)) + 1
    cmin = np.floor(np.nan_to_num(col.min(1), nan=0.0)) - 1
    cmax = np.ceil(np.nan_to_num(col.max(1), nan=0.0)) + 1
    fp[:, 0] = np.clip(rmin, 0, det.rows)
    fp[:, 1] = np.clip(rmax, -1, det.rows - 1)
    fp[:, 2] = np.clip(cmin, 0, det.cols)
    fp[:, 3] = np.clip(cmax, -1, det.cols - 1)
    fp[behind] = (0, det.rows - 1, 0, det.cols - 1)
    # projected size of the smallest semi-axis, in pixels, for supersampling
    cdepth = P[2, :3] @ c.T + P[2, 3]
    mag = geometry.sdd[index] / np.maximum(cdepth, 1e-6)
    size_px = 2 * s.min(axis=1) * mag / min(det.pitch_col, det.pitch_row)
    ss = _supersampling(size_px, supersample)
    if supersample is True:  # wires thinner than half a pixel: exact pixel averages from their mass
        wire = (pk.kind == 1) & (2 * s[:, :2].max(axis=1) * mag / min(det.pitch_col, det.pitch_row) < 0.5)
        for k in np.flatnonzero(wire):
            ax = R[k][:, 2] * s[k, 2]
            ends = np.array([c[k] - ax, c[k] + ax])
            hp = ends @ P[:, :3].T + P[:, 3]
            if (hp[:, 2] <= 0).any():
                continue
            span_px = float(np.hypot(*(hp[1, :2] / hp[1, 2] - hp[0, :2] / hp[0, 2])))
            _deposit_segment(
                out,
                ends[0],
                ends[1],
                max(16, int(np.ceil(50 * span_px))),
                P,
                S,
                P00,
                u,
                v,
                float(geometry.sdd[index]),
                float(pk.mu[k] * np.pi * s[k, 0] * s[k, 1]),
                det.pitch_col * det.pitch_row,
                float(s[k, :2].mean()),
                float(np.sqrt(det.pitch_col * det.pitch_row)),
            )
        fp[wire] = (1, 0, 1, 0)  # nothing left for the chord kernel
    _render(
        out,
        pk.kind,
        np.ascontiguousarray(a),
        np.ascontiguousarray(b00),
        np.ascontiguousarray(bu),
        np.ascontiguousarray(bv),
        pk.mu,
        fp,
        ss,
        P00 - S,
        u.copy(),
        v.copy(),
    )
    return out


def line_integral_stack(
    phantom: Phantom,
    geometry: ViewGeometry,
    indices: NDArray[np.intp] | list[int] | None = None,
    *,
    supersample: bool | int = True,
    beam: Beam | None = None,
    progress: ProgressCallback | None = None,
) -> NDArray[np.float32]:
    """Noise-free line integrals ``(n, rows, cols)`` of the given views (default: every finite view)."""
    idx = np.flatnonzero(geometry.valid) if indices is None else np.asarray(indices, dtype=np.intp)
    out = np.empty((len(idx),) + geometry.panel.shape, dtype=np.float32)
    for k, i in enumerate(idx):
        out[k] = line_integrals(phantom, geometry, int(i), supersample=supersample, beam=beam)
        report(progress, "project", k + 1, len(idx))
    return out
