"""Exact chord lengths of lines through ellipsoids and finite elliptic cylinders (numba kernels).

Every primitive is an affine image of a unit shape: local coordinates ``y = R^T (x - c) / s``
turn it into the unit ball (ellipsoid) or the unit disc times ``[-1, 1]`` (cylinder). A line
``x = o + t d`` becomes ``y = a + t b``; the kernels return the parameter interval length
``dt`` inside the unit shape, so the chord is ``dt * |d|`` in millimetres.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

ELLIPSOID = 0
CYLINDER = 1
_TINY = 1e-300


@nb.njit(cache=True, nogil=True, inline="always")
def chord_dt(kind: int, a0: float, a1: float, a2: float, b0: float, b1: float, b2: float) -> float:
    """Parameter length of the line ``a + t b`` inside the unit ball (kind 0) or unit cylinder (kind 1)."""
    if kind == 0:
        A = b0 * b0 + b1 * b1 + b2 * b2
        B = a0 * b0 + a1 * b1 + a2 * b2
        C = a0 * a0 + a1 * a1 + a2 * a2 - 1.0
        disc = B * B - A * C
        if disc <= 0.0 or A <= _TINY:
            return 0.0
        return 2.0 * math.sqrt(disc) / A
    # cylinder: radial interval
    A = b0 * b0 + b1 * b1
    C = a0 * a0 + a1 * a1 - 1.0
    if A <= _TINY:
        if C > 0.0:
            return 0.0
        t1, t2 = -math.inf, math.inf
    else:
        B = a0 * b0 + a1 * b1
        disc = B * B - A * C
        if disc <= 0.0:
            return 0.0
        sq = math.sqrt(disc)
        t1 = (-B - sq) / A
        t2 = (-B + sq) / A
    # axial slab |a2 + t b2| <= 1
    if abs(b2) <= _TINY:
        if abs(a2) > 1.0:
            return 0.0
        s1, s2 = -math.inf, math.inf
    else:
        s1 = (-1.0 - a2) / b2
        s2 = (1.0 - a2) / b2
        if s1 > s2:
            s1, s2 = s2, s1
    lo = t1 if t1 > s1 else s1
    hi = t2 if t2 < s2 else s2
    if hi <= lo or not math.isfinite(hi - lo):
        return 0.0
    return hi - lo


@nb.njit(cache=True, nogil=True, inline="always")
def inside(kind: int, y0: float, y1: float, y2: float) -> bool:
    """Whether local point ``y`` lies in the unit ball (kind 0) or unit cylinder (kind 1)."""
    if kind == 0:
        return y0 * y0 + y1 * y1 + y2 * y2 <= 1.0
    return y0 * y0 + y1 * y1 <= 1.0 and abs(y2) <= 1.0


@nb.njit(cache=True, nogil=True)
def _chords(kind: int, a: NDArray[np.float64], b: NDArray[np.float64], dn: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.empty(a.shape[0])
    for k in range(a.shape[0]):
        out[k] = chord_dt(kind, a[k, 0], a[k, 1], a[k, 2], b[k, 0], b[k, 1], b[k, 2]) * dn[k]
    return out


@nb.njit(cache=True, nogil=True)
def _weighted_chord_sum(kind, center, rotation, semi_axes, mu, radius, o, d):  # type: ignore[no-untyped-def]
    out = np.zeros(o.shape[0])
    for k in range(o.shape[0]):
        dn = math.sqrt(d[k, 0] ** 2 + d[k, 1] ** 2 + d[k, 2] ** 2)
        if dn <= _TINY:
            continue
        acc = 0.0
        for p in range(kind.shape[0]):
            w0, w1, w2 = o[k, 0] - center[p, 0], o[k, 1] - center[p, 1], o[k, 2] - center[p, 2]
            along = (w0 * d[k, 0] + w1 * d[k, 1] + w2 * d[k, 2]) / dn
            if w0 * w0 + w1 * w1 + w2 * w2 - along * along > radius[p] * radius[p]:
                continue  # the line passes outside the primitive's bounding sphere
            a0 = (w0 * rotation[p, 0, 0] + w1 * rotation[p, 1, 0] + w2 * rotation[p, 2, 0]) / semi_axes[p, 0]
            a1 = (w0 * rotation[p, 0, 1] + w1 * rotation[p, 1, 1] + w2 * rotation[p, 2, 1]) / semi_axes[p, 1]
            a2 = (w0 * rotation[p, 0, 2] + w1 * rotation[p, 1, 2] + w2 * rotation[p, 2, 2]) / semi_axes[p, 2]
            b0 = (d[k, 0] * rotation[p, 0, 0] + d[k, 1] * rotation[p, 1, 0] + d[k, 2] * rotation[p, 2, 0]) / semi_axes[
                p, 0
            ]
            b1 = (d[k, 0] * rotation[p, 0, 1] + d[k, 1] * rotation[p, 1, 1] + d[k, 2] * rotation[p, 2, 1]) / semi_axes[
                p, 1
            ]
            b2 = (d[k, 0] * rotation[p, 0, 2] + d[k, 1] * rotation[p, 1, 2] + d[k, 2] * rotation[p, 2, 2]) / semi_axes[
                p, 2
            ]
            acc += mu[p] * chord_dt(kind[p], a0, a1, a2, b0, b1, b2) * dn
        out[k] = acc
    return out


def weighted_chord_sum(
    kind: NDArray[np.int64],
    center: NDArray[np.float64],
    rotation: NDArray[np.float64],
    semi_axes: NDArray[np.float64],
    mu: NDArray[np.float64],
    origins: ArrayLike,
    directions: ArrayLike,
) -> NDArray[np.float64]:
    """Line integrals ``sum mu * chord`` of lines ``(K, 3)`` through many primitives (arrays over primitives, as
    in :class:`~orbitct.phantoms.phantom.PackedPrimitives`), each primitive skipped where the line misses its
    bounding sphere."""
    o = np.atleast_2d(np.asarray(origins, float))
    d = np.atleast_2d(np.asarray(directions, float))
    o, d = np.broadcast_arrays(o, d)
    s = np.asarray(semi_axes, float)
    radius = np.where(np.asarray(kind) == ELLIPSOID, s.max(1), np.hypot(s[:, :2].max(1), s[:, 2])) * (1 + 1e-9)
    return _weighted_chord_sum(
        np.asarray(kind, np.int64),
        np.ascontiguousarray(center, float),
        np.ascontiguousarray(rotation, float),
        np.ascontiguousarray(s),
        np.asarray(mu, float),
        radius,
        np.ascontiguousarray(o),
        np.ascontiguousarray(d),
    )


def local_frame(center: ArrayLike, rotation: ArrayLike, semi_axes: ArrayLike) -> tuple[NDArray[np.float64], ...]:
    """``(c, R, s)`` as float64 arrays."""
    return np.asarray(center, float), np.asarray(rotation, float), np.asarray(semi_axes, float)


def chord_lengths(
    kind: int,
    center: ArrayLike,
    rotation: ArrayLike,
    semi_axes: ArrayLike,
    origins: ArrayLike,
    directions: ArrayLike,
) -> NDArray[np.float64]:
    """Chord length (mm) of lines ``origin + t direction`` (``(K, 3)`` each) through one primitive."""
    c, R, s = local_frame(center, rotation, semi_axes)
    o = np.atleast_2d(np.asarray(origins, float))
    d = np.atleast_2d(np.asarray(directions, float))
    o, d = np.broadcast_arrays(o, d)
    a = ((o - c) @ R) / s
    b = (d @ R) / s
    return _chords(int(kind), np.ascontiguousarray(a), np.ascontiguousarray(b), np.linalg.norm(d, axis=1))
