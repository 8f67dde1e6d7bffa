"""BB candidates in one frame: disc-kernel correlation on a binned line-integral image, then sub-pixel
centroids refined at full resolution in a small window.

The line integrals follow ``scan-file.md`` (``-log((raw - dark) / (flat - dark))`` with the scan's mean dark and
flat); they are computed from the raw frame only where needed (binned for the search, full resolution in the
windows), so a frame is never held as float64.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import scipy.fft
from numpy.typing import NDArray

from orbitct.defects import DefectMap

#: columns of a candidate record
CANDIDATE_FIELDS = (
    "col",
    "row",
    "score",
    "amplitude",
    "radius_px",
    "elongation",
    "background_rms",
    "paper_col",
    "paper_row",
)
N_FIELDS = len(CANDIDATE_FIELDS)


@numba.njit(cache=True, nogil=True)
def _binned_line_integrals(raw, dark_b, den_b, b):  # type: ignore[no-untyped-def]
    rows, cols = dark_b.shape
    out = np.empty((rows, cols), np.float32)
    acc = np.empty(cols * b, np.float32)  # column sums of the b raw rows of one binned row (exact: integers < 2**24)
    inv = np.float32(1.0 / (b * b))
    for i in range(rows):
        acc[:] = 0.0
        for di in range(b):
            line = raw[i * b + di]
            for j in range(cols * b):
                acc[j] += np.float32(line[j])
        for j in range(cols):
            s = np.float32(0.0)
            for dj in range(b):
                s += acc[j * b + dj]
            num = max(s * inv - dark_b[i, j], np.float32(0.5))
            out[i, j] = -np.log(num / den_b[i, j])
    return out


@numba.njit(cache=True, nogil=True)
def _local_maxima(resp, threshold, max_count, boxes):  # type: ignore[no-untyped-def]
    """The ``max_count`` strongest 3x3 local maxima above ``threshold`` inside ``boxes`` (rows ``(row0, row1, col0,
    col1)``, half-open, at least one pixel inside the image's edge; they may overlap): rows ``(col, row, value)``."""
    rows, cols = resp.shape
    seen = np.zeros((rows, cols), np.bool_)
    found = np.empty((max_count, 3), np.float64)
    n = 0
    weakest = 0
    for k in range(boxes.shape[0]):
        for i in range(boxes[k, 0], boxes[k, 1]):
            for j in range(boxes[k, 2], boxes[k, 3]):
                if seen[i, j]:
                    continue
                seen[i, j] = True
                v = resp[i, j]
                if v < threshold:
                    continue
                if n == max_count and v <= found[weakest, 2]:
                    continue
                is_max = True
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        if (di != 0 or dj != 0) and resp[i + di, j + dj] > v:
                            is_max = False
                if not is_max:
                    continue
                slot = n if n < max_count else weakest
                found[slot, 0] = j
                found[slot, 1] = i
                found[slot, 2] = v
                if n < max_count:
                    n += 1
                if n == max_count:
                    weakest = 0
                    for q in range(1, n):
                        if found[q, 2] < found[weakest, 2]:
                            weakest = q
    return found[:n]


@numba.njit(cache=True, nogil=True)
def solve3(a, y):  # type: ignore[no-untyped-def]
    """Solution of the symmetric 3x3 system ``a x = y`` (Cramer's rule: no LAPACK call per window, and far less
    to compile than ``np.linalg.solve``; NaN for a singular system). Also called by the kernels of
    :mod:`calib.track`, whose cached machine code numba does not renew when this changes: change both files."""
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    x = np.empty(3)
    if det == 0.0:  # (a division by zero raises in a kernel)
        x[:] = np.nan
        return x
    x[0] = (
        y[0] * c00 + a[0, 1] * (a[1, 2] * y[2] - y[1] * a[2, 2]) + a[0, 2] * (y[1] * a[2, 1] - a[1, 1] * y[2])
    ) / det
    x[1] = (
        a[0, 0] * (y[1] * a[2, 2] - a[1, 2] * y[2]) + y[0] * c01 + a[0, 2] * (a[1, 0] * y[2] - y[1] * a[2, 0])
    ) / det
    x[2] = (
        a[0, 0] * (a[1, 1] * y[2] - y[1] * a[2, 1]) + a[0, 1] * (y[1] * a[2, 0] - a[1, 0] * y[2]) + y[0] * c02
    ) / det
    return x


@numba.njit(cache=True, nogil=True)
def _disc_box(fx, fy, r, half):  # type: ignore[no-untyped-def]
    """Window index ranges ``(b0, b1, a0, a1)`` (columns, rows; end exclusive) holding the disc of radius ``r``
    centred ``(fx, fy)`` from the window centre."""
    size = 2 * half + 1
    b0 = max(0, int(np.floor(fx - r)) + half)
    b1 = min(size, int(np.ceil(fx + r)) + half + 1)
    a0 = max(0, int(np.floor(fy - r)) + half)
    a1 = min(size, int(np.ceil(fy + r)) + half + 1)
    return b0, b1, a0, a1


@numba.njit(cache=True, nogil=True)
def _refine(raw, dark, den, col0, row0, radius, half, passes):  # type: ignore[no-untyped-def]
    """Background-plane-subtracted weighted centroid, peak, size, elongation, background RMS, paper centroid."""
    size = 2 * half + 1
    return _refine_in(raw, dark, den, col0, row0, radius, half, passes, np.empty((size, size), np.float64))


@numba.njit(cache=True, nogil=True)
def _refine_in(raw, dark, den, col0, row0, radius, half, passes, li):  # type: ignore[no-untyped-def]
    """:func:`_refine` with a caller-owned window buffer ``li`` (``(2 half + 1)^2``)."""
    rows, cols = raw.shape
    out = np.full(8, np.nan)
    cx, cy = col0, row0
    size = 2 * half + 1
    r_in2 = (radius + 1.0) ** 2
    r_w2 = (radius + 0.75) ** 2
    coef = np.zeros(3)
    ic = 0
    ir = 0
    # sums over the whole window (they change only when the window moves); the background fit uses the window
    # minus the BB's disc, so only a box around the disc is visited per pass
    hk = np.float64(half * (half + 1) * (2 * half + 1) // 3)  # sum of k^2 for k = -half..half
    n_all = np.float64(size * size)
    s_z = 0.0
    s_xz = 0.0
    s_yz = 0.0
    s_zz = 0.0
    r_in = radius + 1.0  # the disc excluded from the background fit; the weighting disc lies inside it
    ata = np.zeros((3, 3))
    atb = np.zeros(3)
    for p in range(passes):
        # the window stays on the panel: near an edge the BB sits off its centre (it must still hold the disc)
        ic_new = min(max(int(np.floor(cx + 0.5)), half), cols - 1 - half)
        ir_new = min(max(int(np.floor(cy + 0.5)), half), rows - 1 - half)
        if ic_new < half or ir_new < half or abs(cx - ic_new) + r_in > half or abs(cy - ir_new) + r_in > half:
            return out
        if p == 0 or ic_new != ic or ir_new != ir:  # the window's line integrals only change when it moves
            ic, ir = ic_new, ir_new
            s_z = 0.0
            s_xz = 0.0
            s_yz = 0.0
            s_zz = 0.0
            for a in range(size):
                r = ir - half + a
                row_z = 0.0
                row_xz = 0.0
                for b in range(size):
                    c = ic - half + b
                    num = max(np.float32(raw[r, c]) - dark[r, c], np.float32(0.5))
                    z = np.float64(-np.log(num / den[r, c]))  # float32 log: twice as fast, 1e-7 relative
                    li[a, b] = z
                    row_z += z
                    row_xz += (b - half) * z
                    s_zz += z * z
                s_z += row_z
                s_xz += row_xz
                s_yz += (a - half) * row_z
        if p == 0 and s_z > 0 and abs(cx - ic) <= 0.5 and abs(cy - ir) <= 0.5:
            # the paper's estimator: plain intensity centroid of the square window (centred on the BB only)
            out[6] = ic + s_xz / s_z
            out[7] = ir + s_yz / s_z
        # background plane z = c0 + c1 x + c2 y fitted to the window outside the BB (x, y about the pixel ic, ir):
        # the whole window's sums minus those inside the disc
        n_in = 0.0
        i_x = 0.0
        i_y = 0.0
        i_xx = 0.0
        i_xy = 0.0
        i_yy = 0.0
        i_z = 0.0
        i_xz = 0.0
        i_yz = 0.0
        b0, b1, a0, a1 = _disc_box(cx - ic, cy - ir, r_in, half)
        for a in range(a0, a1):
            for b in range(b0, b1):
                x = b - half + ic - cx
                y = a - half + ir - cy
                if x * x + y * y < r_in2:
                    xb = np.float64(b - half)
                    yb = np.float64(a - half)
                    z = li[a, b]
                    n_in += 1.0
                    i_x += xb
                    i_y += yb
                    i_xx += xb * xb
                    i_xy += xb * yb
                    i_yy += yb * yb
                    i_z += z
                    i_xz += xb * z
                    i_yz += yb * z
        ata[0, 0] = n_all - n_in
        if ata[0, 0] < 6:
            return out
        ata[0, 1] = ata[1, 0] = -i_x
        ata[0, 2] = ata[2, 0] = -i_y
        ata[1, 1] = size * hk - i_xx
        ata[1, 2] = ata[2, 1] = -i_xy
        ata[2, 2] = size * hk - i_yy
        atb[0] = s_z - i_z
        atb[1] = s_xz - i_xz
        atb[2] = s_yz - i_yz
        coef = solve3(ata, atb)
        w_sum = 0.0
        mx = 0.0
        my = 0.0
        b0, b1, a0, a1 = _disc_box(cx - ic, cy - ir, r_in, half)
        for a in range(a0, a1):
            for b in range(b0, b1):
                x = b - half + ic - cx
                y = a - half + ir - cy
                if x * x + y * y <= r_w2:
                    w = li[a, b] - (coef[0] + coef[1] * (b - half) + coef[2] * (a - half))
                    if w > 0:
                        w_sum += w
                        mx += w * x
                        my += w * y
        if w_sum <= 0:
            return out
        cx = cx + mx / w_sum
        cy = cy + my / w_sum
    # residual of the plane outside the disc: sum of w^2 over the window minus inside, w = z - f.coef
    peak = 0.0
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    w_sum = 0.0
    n_in = 0.0
    in_ww = 0.0
    b0, b1, a0, a1 = _disc_box(cx - ic, cy - ir, r_in, half)
    for a in range(a0, a1):
        for b in range(b0, b1):
            x = b - half + ic - cx
            y = a - half + ir - cy
            w = li[a, b] - (coef[0] + coef[1] * (b - half) + coef[2] * (a - half))
            if x * x + y * y < r_in2:
                n_in += 1.0
                in_ww += w * w
            if x * x + y * y <= r_w2:
                peak = max(peak, w)
                if w > 0:
                    w_sum += w
                    sxx += w * x * x
                    syy += w * y * y
                    sxy += w * x * y
    c0, c1, c2 = coef[0], coef[1], coef[2]
    # sum over the window of (z - c0 - c1 x - c2 y)^2 from its moments (sum x = sum y = sum xy = 0)
    all_ww = s_zz - 2.0 * (c0 * s_z + c1 * s_xz + c2 * s_yz) + c0 * c0 * n_all + (c1 * c1 + c2 * c2) * size * hk
    rss = max(all_ww - in_ww, 0.0)
    n_ring = n_all - n_in
    if w_sum <= 0 or n_ring == 0:
        return out
    sxx /= w_sum
    syy /= w_sum
    sxy /= w_sum
    tr = sxx + syy
    det = sxx * syy - sxy * sxy
    disc = np.sqrt(max(tr * tr / 4 - det, 0.0))
    l1 = tr / 2 + disc
    l2 = max(tr / 2 - disc, 1e-12)
    out[0] = cx
    out[1] = cy
    out[2] = peak
    out[3] = np.sqrt(2.5 * tr)  # a projected ball of radius R has <r^2> = 2 R^2 / 5
    out[4] = np.sqrt(l1 / l2)
    out[5] = np.sqrt(rss / n_ring)
    return out


@numba.njit(cache=True, nogil=True)
def _refine_all(raw, dark, den, peaks, b, radius, half, passes, noise):  # type: ignore[no-untyped-def]
    """Candidate records for binned peaks ``(M, 3)`` = (col, row, response)."""
    out = np.full((peaks.shape[0], N_FIELDS), np.nan)
    li = np.empty((2 * half + 1, 2 * half + 1), np.float64)
    for m in range(peaks.shape[0]):
        col0 = peaks[m, 0] * b + 0.5 * (b - 1)
        row0 = peaks[m, 1] * b + 0.5 * (b - 1)
        rec = _refine_in(raw, dark, den, col0, row0, radius, half, passes, li)
        out[m, 0] = rec[0]
        out[m, 1] = rec[1]
        out[m, 2] = peaks[m, 2] / noise
        for q in range(4):
            out[m, 3 + q] = rec[2 + q]
        out[m, 7] = rec[6]
        out[m, 8] = rec[7]
    return out


def _disc_kernel(radius: float) -> NDArray[np.float64]:
    """A zero-mean kernel ``(2h + 1, 2h + 1)``: disc of ``radius`` minus the surrounding ring (binned pixels)."""
    r_out = 2.0 * radius + 1.5
    h = int(np.ceil(r_out))
    y, x = np.mgrid[-h : h + 1, -h : h + 1]
    rr = np.hypot(x, y)
    disc = (rr <= radius + 0.5).astype(np.float64)
    ring = ((rr > radius + 1.0) & (rr <= r_out)).astype(np.float64)
    return np.asarray(disc / disc.sum() - ring / max(ring.sum(), 1.0))


def _disc_kernel_spectrum(shape: tuple[int, int], radius: float) -> NDArray[np.complex64]:
    """Spectrum of :func:`_disc_kernel` on an image of ``shape`` (correlation by multiplication)."""
    k = _disc_kernel(radius)
    h = k.shape[0] // 2
    full = np.zeros(shape)
    full[: k.shape[0], : k.shape[1]] = k[::-1, ::-1]
    full = np.roll(full, (-h, -h), axis=(0, 1))
    return scipy.fft.rfft2(full).astype(np.complex64)


def _disc_kernel_rows(radius: float) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], float, float]:
    """:func:`_disc_kernel` as runs along its rows: per row, the half-widths of the disc, of the ring's outer
    and of its inner edge (-1: none), and the weights of the disc and the ring."""
    k = _disc_kernel(radius)
    h = k.shape[0] // 2
    y, x = np.mgrid[-h : h + 1, -h : h + 1]
    rr = np.hypot(x, y)
    disc, outer, inner = rr <= radius + 0.5, rr <= 2.0 * radius + 1.5, rr <= radius + 1.0
    ring = outer & ~inner
    widths = [(m.sum(axis=1) - 1) // 2 for m in (disc, outer, inner)]
    return widths[0], widths[1], widths[2], 1.0 / disc.sum(), 1.0 / max(ring.sum(), 1)


@numba.njit(cache=True, nogil=True)
def _window_response(raw, dark_b, den_b, b, rows_d, rows_o, rows_i, w_disc, w_ring, boxes):  # type: ignore[no-untyped-def]
    """The disc-kernel correlation of the binned line integrals in ``boxes`` (rows ``(row0, row1, col0, col1)``,
    binned) and one pixel round each, the image extended by its edge values as :meth:`FrameDetector.response`
    does; zero elsewhere. The kernel comes as runs along its rows (:func:`_disc_kernel_rows`), summed from
    running sums of the line integrals."""
    rows, cols = dark_b.shape
    h = rows_d.shape[0] // 2
    resp = np.zeros((rows, cols), np.float32)
    li = np.empty((rows, cols), np.float32)
    done = np.zeros((rows, cols), np.bool_)
    acc = np.empty(cols * b, np.float32)
    inv = np.float32(1.0 / (b * b))
    for k in range(boxes.shape[0]):
        r0, r1 = max(boxes[k, 0] - 1, 0), min(boxes[k, 1] + 1, rows)
        c0, c1 = max(boxes[k, 2] - 1, 0), min(boxes[k, 3] + 1, cols)
        if r1 <= r0 or c1 <= c0:
            continue
        ca, cb = max(c0 - h, 0), min(c1 + h, cols)
        for i in range(max(r0 - h, 0), min(r1 + h, rows)):  # the binned line integrals the window needs
            acc[ca * b : cb * b] = 0.0
            for di in range(b):
                line = raw[i * b + di]
                for x in range(ca * b, cb * b):
                    acc[x] += np.float32(line[x])
            for j in range(ca, cb):
                if not done[i, j]:
                    s = np.float32(0.0)
                    for dj in range(b):
                        s += acc[j * b + dj]
                    num = max(s * inv - dark_b[i, j], np.float32(0.5))
                    li[i, j] = -np.log(num / den_b[i, j])
                    done[i, j] = True
        pr, pc = r1 - r0 + 2 * h, c1 - c0 + 2 * h
        run = np.empty((pr, pc + 1), np.float64)  # run[r, j]: the sum of patch row r's first j line integrals
        for pi in range(pr):
            row = min(max(r0 - h + pi, 0), rows - 1)
            run[pi, 0] = 0.0
            for pj in range(pc):
                run[pi, pj + 1] = run[pi, pj] + li[row, min(max(c0 - h + pj, 0), cols - 1)]
        out = np.empty(c1 - c0, np.float64)
        for i in range(r0, r1):
            out[:] = 0.0
            for dy in range(-h, h + 1):
                line = run[i - r0 + h + dy]
                wd, wo, wi = rows_d[dy + h], rows_o[dy + h], rows_i[dy + h]
                for j in range(c1 - c0):
                    x = j + h  # the pixel's column in the patch
                    v = 0.0
                    if wd >= 0:
                        v += w_disc * (line[x + wd + 1] - line[x - wd])
                    if wo >= 0:
                        v -= w_ring * (line[x + wo + 1] - line[x - wo])
                    if wi >= 0:
                        v += w_ring * (line[x + wi + 1] - line[x - wi])
                    out[j] += v
            for j in range(c1 - c0):  # boxes may overlap: written, not added
                resp[i, c0 + j] = out[j]
    return resp


#: bounds of a detection's spread relative to the scan's typical one (:func:`detection_spread`)
SPREAD_RANGE = (0.5, 5.0)


def detection_spread(cands: list[NDArray[np.float64]], uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each detection's expected centroid error relative to the scan's typical one ``(N, K)``: the RMS of the
    background plane's residual round it (``background_rms``: photon noise and structure the plane cannot follow,
    such as the object's outline), over the median of the detections in ``uv`` (per frame, looked up in the frame's
    candidates ``cands`` by position), within :data:`SPREAD_RANGE`; 1 where ``uv`` holds a position no candidate
    has (a blob split in two). A BB crossing the object's outline is off by 2-5 times the typical error there."""
    n, k = uv.shape[:2]
    rms = np.full((n, k), np.nan)
    field = CANDIDATE_FIELDS.index("background_rms")
    for p in range(n):
        c = cands[p]
        if not len(c):
            continue
        hit = (c[None, :, 0] == uv[p, :, None, 0]) & (c[None, :, 1] == uv[p, :, None, 1])  # (K, M)
        found = hit.any(1)
        rms[p, found] = c[hit.argmax(1)[found], field]
    return relative_spread(rms)


def relative_spread(rms: NDArray[np.float64]) -> NDArray[np.float64]:
    """Background RMS values (NaN: unknown) over their median, within :data:`SPREAD_RANGE`; 1 where unknown."""
    known = np.isfinite(rms)
    typical = float(np.median(rms[known])) if known.any() else 0.0
    if not typical > 0:
        return np.ones(rms.shape)
    return np.where(known, np.clip(rms / typical, *SPREAD_RANGE), 1.0)


#: the strongest peaks are kept per area searched: an object full of structure (a torso's spine, ribs and screws
#: seen from the side) can fill a fixed number with peaks stronger than its BBs (experiment C at 512 px: 5 of 10
#: BBs among the 128 strongest peaks of a lateral view, all 10 among 256)
CANDIDATE_AREA_PX = 1024


@dataclass
class DetectorSettings:
    """How BBs are searched for in one frame (pixel sizes at full resolution)."""

    diameter_px: float
    binning: int
    k_sigma: float = 6.0
    max_candidates: int = 128  # at least; a larger searched image keeps one per CANDIDATE_AREA_PX binned pixels
    refine_passes: int = 3


def settings_for(diameter_px: float, shape: tuple[int, int]) -> DetectorSettings:
    """Binning so the BB spans about 2.5-5 binned pixels."""
    b = max(1, int(diameter_px // 2.5))
    while b > 1 and (shape[0] % b or shape[1] % b):
        b -= 1
    return DetectorSettings(diameter_px=float(diameter_px), binning=b)


@dataclass(frozen=True)
class FrameSearch:
    """What one search of a frame found: candidate records, and the weakest score kept when it kept the most
    peaks it may (else 0): a search of windows only ignores weaker peaks, as the whole frame's search would."""

    records: NDArray[np.float64]
    floor: float


class FrameDetector:
    """Finds BB candidates in raw frames of one scan (fixed dark, flat and BB size)."""

    def __init__(self, dark: NDArray[np.float32], flat: NDArray[np.float32], settings: DetectorSettings) -> None:
        self.settings = settings
        b = settings.binning
        rows, cols = dark.shape
        self.shape = (rows, cols)
        # pixels that do not respond (dead pixels and columns) are filled from their row neighbours, in the dark and
        # flat here and in every frame searched: normalised, they would read as infinite line integrals
        self.defects = DefectMap.from_dark_flat(dark, flat)
        dark, flat = self.defects.filled(dark), self.defects.filled(flat)
        self.dark = np.ascontiguousarray(dark, dtype=np.float32)
        self.den = np.maximum(flat - dark, 1.0).astype(np.float32)
        rb, cb = rows // b, cols // b
        self.dark_b = self.dark[: rb * b, : cb * b].reshape(rb, b, cb, b).mean((1, 3)).astype(np.float32)
        self.den_b = self.den[: rb * b, : cb * b].reshape(rb, b, cb, b).mean((1, 3)).astype(np.float32)
        self.radius_b = max(0.5 * settings.diameter_px / b, 0.75)
        # the correlation runs on the image padded with its edge values, so BBs near an edge are not blurred
        # with the opposite edge (a circular convolution wraps around)
        self.pad = int(np.ceil(2.0 * self.radius_b + 1.5)) + 1
        self.padded = (
            scipy.fft.next_fast_len(rb + 2 * self.pad, real=True),
            scipy.fft.next_fast_len(cb + 2 * self.pad, real=True),
        )
        self._kernel = _disc_kernel_spectrum(self.padded, self.radius_b)
        self._kernel_rows = _disc_kernel_rows(self.radius_b)
        self.border = int(np.ceil(self.radius_b))  # peaks searched wherever a whole BB fits on the panel
        self.noise_border = int(np.ceil(2 * self.radius_b + 2))
        self.half = int(np.ceil(settings.diameter_px)) + 2
        self.noise: float | None = None
        self.noise_factor = 1.0  # the panel's noise correlation (:meth:`measure_noise_correlation`)

    def response(self, raw: NDArray[np.generic]) -> NDArray[np.float32]:
        """Disc-kernel correlation of the binned line-integral image."""
        li = _binned_line_integrals(raw, self.dark_b, self.den_b, self.settings.binning)
        rb, cb = li.shape
        pr, pc, q = self.padded[0] - rb, self.padded[1] - cb, self.pad
        big = np.pad(li, ((q, pr - q), (q, pc - q)), mode="edge")
        resp = scipy.fft.irfft2(scipy.fft.rfft2(big) * self._kernel, s=big.shape)
        return np.ascontiguousarray(resp[q : q + rb, q : q + cb], dtype=np.float32)

    def estimate_noise(self, raw: NDArray[np.generic]) -> float:
        """Standard deviation of the response due to pixel noise: the binned line integrals' noise (robust, from
        differences of neighbouring pixels, so edges of the object do not count) through the kernel, times the
        panel's noise correlation (:attr:`noise_factor`). Structure in the image is not noise: a frame filled by
        the object would otherwise raise the threshold above faint BBs."""
        li = _binned_line_integrals(self.defects.filled(raw), self.dark_b, self.den_b, self.settings.binning)
        return self._white_response_noise(li) * self.noise_factor + 1e-9

    def _white_response_noise(self, li: NDArray[np.floating[Any]]) -> float:
        """The response's noise if the pixels' noise were independent: their spread (robust, from differences of
        neighbours) times the kernel's norm."""
        e = self.noise_border
        dif = np.diff(li[e:-e, e:-e], axis=1).ravel()
        pixel = 1.4826 * float(np.median(np.abs(dif - np.median(dif)))) / np.sqrt(2.0)
        kernel = scipy.fft.irfft2(self._kernel, s=self.padded)
        return pixel * float(np.sqrt((kernel**2).sum()))

    def measure_noise_correlation(self, flat_a: NDArray[np.generic], flat_b: NDArray[np.generic]) -> float:
        """Set :attr:`noise_factor` from two single flats: the response's true noise over what independent pixel
        noise would give. A scintillator spreads each quantum's light over its neighbours, so their noise is
        correlated: neighbouring differences then understate it and the kernel passes more of it (a threshold of
        independent noise lets noise peaks in by the dozen). Within 5 % of independent noise (what that
        measurement can tell apart) the factor stays 1."""
        b = self.settings.binning
        rb, cb = self.dark_b.shape
        a64 = self.defects.filled(np.asarray(flat_a)).astype(np.float64)
        b64 = self.defects.filled(np.asarray(flat_b)).astype(np.float64)
        noise = ((a64 - b64)[: rb * b, : cb * b].reshape(rb, b, cb, b).mean((1, 3)) / np.sqrt(2.0)) / self.den_b
        big = np.zeros(self.padded)
        big[:rb, :cb] = noise
        resp = scipy.fft.irfft2(scipy.fft.rfft2(big) * self._kernel, s=big.shape)
        e = self.noise_border
        inner = resp[e : rb - e, e : cb - e]
        true = 1.4826 * float(np.median(np.abs(inner - np.median(inner))))
        white = self._white_response_noise(noise)
        factor = true / white if white > 0 else 1.0
        self.noise_factor = factor if factor > 1.05 else 1.0
        return factor

    def candidates(
        self,
        raw: NDArray[np.generic],
        near: NDArray[np.float64] | None = None,
        reach_px: float | NDArray[np.float64] = 0.0,
    ) -> NDArray[np.float64]:
        """Candidate records ``(M, N_FIELDS)`` (see ``CANDIDATE_FIELDS``), strongest first: in the whole frame, or
        with ``near`` (K, 2) positions (col, row) only within ``reach_px`` (one, or one each) of them in each
        direction."""
        return self.search(raw, near, reach_px).records

    def search(
        self,
        raw: NDArray[np.generic],
        near: NDArray[np.float64] | None = None,
        reach_px: float | NDArray[np.float64] = 0.0,
        floor: float = 0.0,
    ) -> FrameSearch:
        """:meth:`candidates`, keeping only peaks of at least ``floor`` (a score: response over noise), and the
        floor this search set: the weakest peak kept when more were found than are kept (else 0)."""
        s = self.settings
        raw = self.defects.filled(raw)
        if self.noise is None:
            self.noise = self.estimate_noise(raw)
        boxes = self._boxes(self.dark_b.shape, near, reach_px)
        if near is None:
            resp = self.response(raw)
        else:  # the windows only, directly (a few hundred binned pixels each)
            resp = _window_response(raw, self.dark_b, self.den_b, s.binning, *self._kernel_rows, boxes)
        cap = max(s.max_candidates, resp.size // CANDIDATE_AREA_PX)
        peaks = _local_maxima(resp, max(s.k_sigma, floor) * self.noise, cap, boxes)
        peaks = peaks[np.argsort(-peaks[:, 2])]
        out = _refine_all(
            raw, self.dark, self.den, peaks, s.binning, 0.5 * s.diameter_px, self.half, s.refine_passes, self.noise
        )
        keep = np.isfinite(out[:, 0])
        return FrameSearch(out[keep], float(peaks[-1, 2] / self.noise) if len(peaks) == cap else 0.0)

    def _boxes(
        self, shape: tuple[int, int], near: NDArray[np.float64] | None, reach_px: float | NDArray[np.float64]
    ) -> NDArray[np.int64]:
        """Where peaks are searched in the binned response: the whole image less its border, or the squares of
        half-side ``reach_px`` (one, or one each) round the positions ``near`` (col, row at full resolution)."""
        rows, cols = shape
        e = max(self.border, 1)
        if near is None:
            return np.array([[e, rows - e, e, cols - e]], np.int64)
        b = self.settings.binning
        centre = (np.asarray(near, np.float64).reshape(-1, 2) - 0.5 * (b - 1)) / b
        half = np.reshape(np.asarray(reach_px, np.float64), (-1, 1)) / b
        lo = np.floor(centre - half).astype(np.int64)
        hi = np.ceil(centre + half).astype(np.int64) + 1
        boxes = np.stack(
            [
                np.clip(lo[:, 1], e, rows - e),
                np.clip(hi[:, 1], e, rows - e),
                np.clip(lo[:, 0], e, cols - e),
                np.clip(hi[:, 0], e, cols - e),
            ],
            axis=1,
        )
        return np.ascontiguousarray(boxes, np.int64)
