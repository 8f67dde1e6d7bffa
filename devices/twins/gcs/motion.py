"""Straight-line motion with a trapezoidal velocity profile, as a servo controller plans it.

Positions are computed from the clock when asked, so no thread has to tick:
``position(now)`` interpolates between the start and the target of the current
move. All axes of a move arrive together (the hexapod moves this way; a
one-axis stage is the special case). Stuck axes (an injected fault) stay where
they were and never report on target.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray


def profile_fraction(t: float, distance: float, v_max: float, accel: float) -> tuple[float, float]:
    """Fraction of ``distance`` covered after ``t`` seconds, and the total travel time."""
    if distance <= 0.0:
        return 1.0, 0.0
    t_acc = v_max / accel
    d_acc = 0.5 * accel * t_acc**2
    if 2 * d_acc >= distance:  # triangular profile
        t_acc = math.sqrt(distance / accel)
        v_peak, total = accel * t_acc, 2 * t_acc
        d_acc = 0.5 * distance
    else:
        v_peak, total = v_max, 2 * t_acc + (distance - 2 * d_acc) / v_max
    if t <= 0.0:
        return 0.0, total
    if t >= total:
        return 1.0, total
    if t < t_acc:
        d = 0.5 * accel * t**2
    elif t < total - t_acc:
        d = d_acc + v_peak * (t - t_acc)
    else:
        r = total - t
        d = distance - 0.5 * accel * r**2
    return min(1.0, d / distance), total


class LinearMotion:
    """Controller-side (commanded/encoder) positions of a group of axes moving on straight lines."""

    def __init__(
        self, axes: Sequence[str], start: Sequence[float], *, time_scale: float = 1.0, clock: object = time.monotonic
    ) -> None:
        self.axes = tuple(axes)
        self.time_scale = float(time_scale)
        self._clock = clock
        self._start = np.asarray(start, dtype=float).copy()
        self.target = self._start.copy()
        self._t0 = 0.0
        self._duration = 0.0
        self._speed = np.ones(len(self.axes))
        self._accel = np.ones(len(self.axes))
        self.stuck = np.zeros(len(self.axes), dtype=bool)
        self.last_direction = np.zeros(len(self.axes))

    def now(self) -> float:
        """Simulation time in seconds (wall clock times ``time_scale``)."""
        return self._clock() * self.time_scale  # type: ignore[operator]

    def _fraction(self, now: float) -> float:
        if self._duration <= 0.0:
            return 1.0
        dist = float(np.max(np.abs(self.target - self._start) / self._speed))
        f, _ = profile_fraction(now - self._t0, dist, 1.0, float(np.min(self._accel / self._speed)))
        return f

    def position(self, now: float | None = None) -> NDArray[np.float64]:
        """Where the controller's encoders are now."""
        now = self.now() if now is None else now
        f = self._fraction(now)
        pos = self._start + f * (self.target - self._start)
        pos[self.stuck] = self._start[self.stuck]
        return pos

    def moving(self, now: float | None = None) -> NDArray[np.bool_]:
        """Per axis: still travelling (stuck axes with a pending target count as moving)."""
        now = self.now() if now is None else now
        left = now - self._t0 < self._duration
        diff = np.abs(self.target - self._start) > 1e-12
        return diff & (left | self.stuck)

    def on_target(self, now: float | None = None) -> NDArray[np.bool_]:
        """Per axis: reached the target (within one nanometre or micro-degree)."""
        return np.abs(self.position(now) - self.target) < 1e-9

    def start_move(self, target: ArrayLike, speed: ArrayLike, accel: ArrayLike) -> float:
        """Begin a synchronised move to ``target``; returns its duration (simulation seconds)."""
        now = self.now()
        start = self.position(now)
        goal = np.array(target, dtype=float)
        step = goal - start
        moved = np.abs(step) > 1e-12
        self.last_direction = np.where(moved, np.sign(step), self.last_direction)
        self._start, self.target = start, goal
        self._speed = np.maximum(np.asarray(speed, dtype=float), 1e-9)
        self._accel = np.maximum(np.asarray(accel, dtype=float), 1e-9)
        dist = float(np.max(np.abs(step) / self._speed))
        _, self._duration = profile_fraction(0.0, dist, 1.0, float(np.min(self._accel / self._speed)))
        self._t0 = now
        return self._duration

    def halt(self) -> None:
        """Stop where the axes are now (the real controller decelerates; ours stops at once)."""
        pos = self.position()
        self._start, self.target, self._duration = pos.copy(), pos.copy(), 0.0
