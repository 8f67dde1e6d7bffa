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
    """Learns a scan's pace frame by frame and predicts how long the frames still to come take."""

    def __init__(
        self,
        frames: Sequence[FramePlan],
        travel_s: Callable[[Mapping[str, float], Mapping[str, float]], float],
        settle_s: float,
    ) -> None:
        self._kind = np.array([f.image_key for f in frames], dtype=int)
        # the travel of the move before each frame (the first from wherever the axes are: unknown, taken as none)
        self._travel = np.zeros(len(frames))
        self._moves = np.zeros(len(frames), dtype=bool)
        for k in range(1, len(frames)):
            if frames[k].targets != frames[k - 1].targets:
                self._moves[k] = True
                self._travel[k] = float(travel_s(frames[k - 1].targets, frames[k].targets))
        self._settle_s = float(settle_s)
        self._moved: list[tuple[float, float]] = []  # (travel, seconds) of the moves measured
        self._rest: dict[int, list[float]] = {}  # per image key: seconds of each frame besides its move

    def moved(self, k: int, seconds: float) -> None:
        """The move before frame ``k`` took ``seconds`` (settling included)."""
        if self._moves[k]:
            self._moved.append((float(self._travel[k]), float(seconds)))

    def took(self, k: int, seconds: float) -> None:
        """Frame ``k`` took ``seconds`` besides its move."""
        self._rest.setdefault(int(self._kind[k]), []).append(float(seconds))

    @property
    def projections_seen(self) -> int:
        """Projections measured so far."""
        return len(self._rest.get(int(ImageKey.PROJECTION), []))

    def move_model(self) -> tuple[float, float]:
        """Offset (s) and factor of ``seconds = offset + factor * travel``, fitted with the prior."""
        w = PRIOR_WEIGHT
        a = np.array([[w, 0.0], [0.0, w]])
        b = np.array([w * self._settle_s, w * 1.0])
        for travel, seconds in self._moved:
            x = np.array([1.0, travel])
            a += np.outer(x, x)
            b += x * seconds
        offset, factor = np.linalg.solve(a, b)
        return max(float(offset), 0.0), max(float(factor), 0.0)

    def seconds_left(self, next_frame: int) -> float | None:
        """Expected seconds of frames ``next_frame`` onwards; None until a frame was measured."""
        if not self._rest:
            return None
        means = {kind: float(np.mean(v)) for kind, v in self._rest.items()}
        fallback = max(means.values())  # a kind not yet seen: as the slowest seen (projections render the most)
        offset, factor = self.move_model()
        kinds = self._kind[next_frame:]
        rest = sum(means.get(int(kind), fallback) for kind in kinds)
        moves = self._moves[next_frame:]
        return float(rest + np.sum(moves * (offset + factor * self._travel[next_frame:])))


__all__ = ["ScanPace"]
