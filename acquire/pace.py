"""How long the rest of a step-mode scan takes on this rig, learned from the frames taken so far.

A move's wall time is modelled as ``offset + factor * travel``, where ``travel`` is what the rig says the move takes
at its configured speeds (:meth:`acquire.rig.Rig.travel_s`, no acceleration); offset (acceleration, settling,
hand-shakes) and factor are fitted to the moves measured so far, pulled towards ``settle`` and 1 while few are
known. The rest of a frame (read-backs, exposure, read-out or rendering, recording) is the mean measured for its
kind (dark, flat, projection). Nothing here touches a device.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from acquire.plan import FramePlan
from orbitct.scanfile.keys import ImageKey

PRIOR_WEIGHT = 1.0  # how many moves' worth the prior (offset = settle, factor = 1) weighs


class ScanPace:
    """Learns a scan's pace frame by frame and predicts how long the frames still to come take (each call in constant
    time: it runs on the acquisition's event loop once a frame)."""

    def __init__(
        self,
        frames: Sequence[FramePlan],
        travel_s: Callable[[Mapping[str, float], Mapping[str, float]], float],
        settle_s: float,
    ) -> None:
        n = len(frames)
        self._kind = np.array([f.image_key for f in frames], dtype=int)
        # the travel of the move before each frame (the first from wherever the axes are: unknown, taken as none)
        self._travel = np.zeros(n)
        self._moves = np.zeros(n, dtype=bool)
        for k in range(1, n):
            if frames[k].targets != frames[k - 1].targets:
                self._moves[k] = True
                self._travel[k] = float(travel_s(frames[k - 1].targets, frames[k].targets))
        # from frame k onwards: how many moves, their travel, and how many frames of each kind (suffix sums)
        self._moves_after = np.append(np.cumsum(self._moves[::-1])[::-1], 0)
        self._travel_after = np.append(np.cumsum(self._travel[::-1])[::-1], 0.0)
        self._kinds_after = {
            int(kind): np.append(np.cumsum((self._kind == kind)[::-1])[::-1], 0) for kind in np.unique(self._kind)
        }
        # the move model's normal equations, starting from the prior (offset = settle, factor = 1)
        self._normal = PRIOR_WEIGHT * np.eye(2)
        self._rhs = PRIOR_WEIGHT * np.array([float(settle_s), 1.0])
        self._rest: dict[int, tuple[int, float]] = {}  # per image key: frames measured, their seconds besides moves

    def moved(self, k: int, seconds: float) -> None:
        """The move before frame ``k`` took ``seconds`` (settling included)."""
        if self._moves[k]:
            x = np.array([1.0, self._travel[k]])
            self._normal += np.outer(x, x)
            self._rhs += x * float(seconds)

    def took(self, k: int, seconds: float) -> None:
        """Frame ``k`` took ``seconds`` besides its move."""
        count, total = self._rest.get(int(self._kind[k]), (0, 0.0))
        self._rest[int(self._kind[k])] = (count + 1, total + float(seconds))

    @property
    def projections_seen(self) -> int:
        """Projections measured so far."""
        return self._rest.get(int(ImageKey.PROJECTION), (0, 0.0))[0]

    def move_model(self) -> tuple[float, float]:
        """Offset (s) and factor of ``seconds = offset + factor * travel``, fitted with the prior."""
        offset, factor = np.linalg.solve(self._normal, self._rhs)
        return max(float(offset), 0.0), max(float(factor), 0.0)

    def seconds_left(self, next_frame: int) -> float | None:
        """Expected seconds of frames ``next_frame`` onwards; None until a frame was measured."""
        if not self._rest:
            return None
        means = {kind: total / count for kind, (count, total) in self._rest.items()}
        fallback = max(means.values())  # a kind not yet seen: as the slowest seen (projections render the most)
        offset, factor = self.move_model()
        rest = sum(means.get(kind, fallback) * float(after[next_frame]) for kind, after in self._kinds_after.items())
        return float(rest + offset * self._moves_after[next_frame] + factor * self._travel_after[next_frame])


__all__ = ["ScanPace"]
