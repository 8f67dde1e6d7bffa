"""Sampling each orbit kind into per-frame rotation/tilt angles (radians)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from orbitct.orbits.params import (
    CircularParams,
    DCArcParams,
    MultiArcParams,
    RotationArc,
    SawtoothParams,
    TiltArc,
    WaypointsParams,
)

Angles = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]


def _closed(range_deg: float) -> bool:
    r = abs(range_deg) % 360.0
    return min(r, 360.0 - r) < 1e-9


def _ramp(start: float, span: float, n: int, closed: bool) -> NDArray[np.float64]:
    """``n`` evenly spaced values from ``start`` over ``span``; the end is left out for closed circles."""
    return start + span * np.arange(n) / (n if closed else max(n - 1, 1))


def split_frames(lengths: list[float], n_frames: int) -> list[int]:
    """Frames per segment proportional to angular length (largest remainder, at least 2 each)."""
    w = np.asarray(lengths, dtype=float)
    exact = n_frames * w / w.sum()
    n = np.floor(exact).astype(int)
    for i in np.argsort(-(exact - n))[: n_frames - n.sum()]:
        n[i] += 1
    while (n < 2).any():
        n[np.argmin(n)] += 1
        n[np.argmax(n)] -= 1
    return [int(x) for x in n]


def circular(p: CircularParams) -> Angles:
    th = _ramp(p.start_deg, p.range_deg, p.n_frames, _closed(p.range_deg))
    return np.radians(th), np.full(p.n_frames, np.radians(p.tilt_deg)), np.zeros(p.n_frames, np.int64)


def triangle(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit triangle wave of period 1: 0 -> +1 -> 0 -> -1 -> 0, constant slope."""
    f = np.mod(x, 1.0)
    return np.where(f < 0.25, 4 * f, np.where(f < 0.75, 2 - 4 * f, 4 * f - 4))


def sawtooth(p: SawtoothParams) -> Angles:
    closed = _closed(p.range_deg)
    s = np.arange(p.n_frames) / (p.n_frames if closed else p.n_frames - 1)
    th = p.start_deg + p.range_deg * s
    ph = p.amplitude_deg * triangle(p.cycles * s)
    return np.radians(th), np.radians(ph), np.zeros(p.n_frames, np.int64)


def _arcs(arcs: list[RotationArc | TiltArc], n_frames: int) -> Angles:
    lengths = [abs(a.end_deg - a.start_deg) for a in arcs]
    counts = split_frames(lengths, n_frames)
    th, ph, seg = [], [], []
    for k, (a, n) in enumerate(zip(arcs, counts)):
        span = a.end_deg - a.start_deg
        if isinstance(a, RotationArc):
            th.append(_ramp(a.start_deg, span, n, _closed(span)))
            ph.append(np.full(n, a.tilt_deg))
        else:
            th.append(np.full(n, a.rotation_deg))
            ph.append(_ramp(a.start_deg, span, n, False))
        seg.append(np.full(n, k, np.int64))
    return np.radians(np.concatenate(th)), np.radians(np.concatenate(ph)), np.concatenate(seg)


def dcarc(p: DCArcParams) -> Angles:
    arcs: list[RotationArc | TiltArc] = [
        RotationArc(tilt_deg=t, start_deg=p.start_deg, end_deg=p.start_deg + p.circle_range_deg)
        for t in p.circle_tilts_deg
    ]
    arcs.append(TiltArc(rotation_deg=p.arc_rotation_deg, start_deg=p.arc_start_deg, end_deg=p.arc_end_deg))
    return _arcs(arcs, p.n_frames)


def multiarc(p: MultiArcParams) -> Angles:
    return _arcs(p.resolved_arcs(), p.n_frames)


def waypoints(p: WaypointsParams) -> Angles:
    pts = np.asarray(p.points, dtype=float)
    step = np.hypot(*np.diff(pts, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(step)])
    if s[-1] <= 0:
        raise ValueError("waypoints do not move: all points are the same")
    keep = np.concatenate([[True], step > 0])
    s, pts = s[keep], pts[keep]
    q = np.linspace(0.0, s[-1], p.n_frames)
    th = np.interp(q, s, pts[:, 0])
    ph = np.interp(q, s, pts[:, 1])
    return np.radians(th), np.radians(ph), np.zeros(p.n_frames, np.int64)
