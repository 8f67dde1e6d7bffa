"""Metric scale from a scale bar: two BBs taped at a distance measured on the bench.

A calibration from BBs at unknown places cannot see metric scale: with free per-view poses, making the object
and every source-to-object distance ``s`` times larger (the source-detector assembly unchanged) moves no pixel.
The bundle therefore keeps the size of the BBs' first triangulation through the nominal geometry, which is as
far off as the orbit's mean error along the beam (1-2 % on the bench profile). A known distance between two BBs
removes that: the constellation and every view are rescaled so that the pair is as far apart as measured.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import NDArray

from calib.errors import OptionError
from orbitct.geometry import ViewGeometry

DEFAULT_TOLERANCE = 0.03  # a pair is taken for the scale bar when its calibrated distance is within 3 % of the bar


@dataclass(frozen=True)
class ScaleBar:
    """The pair of BBs (0-based, in the calibration's order) that spans the bar, and the factor applied."""

    bbs: tuple[int, int]
    length_mm: float
    found_mm: float  # their distance before rescaling

    @property
    def factor(self) -> float:
        """How much larger the calibrated frame became."""
        return self.length_mm / self.found_mm

    def describe(self) -> str:
        """One line for the file, the report and the terminal."""
        i, j = self.bbs
        return (
            f"metric scale from a {self.length_mm:g} mm scale bar: BBs {i + 1} and {j + 1} were {self.found_mm:.3f} mm "
            f"apart, so the frame was scaled by {self.factor:.5f}"
        )


class ScaleBarError(OptionError):
    """The scale bar cannot be found among the BBs (no pair, or several pairs, near its length)."""


def find_scale_bar(
    xyz: NDArray[np.float64], length_mm: float, bbs: Sequence[int] | None = None, tolerance: float = DEFAULT_TOLERANCE
) -> ScaleBar:
    """The pair of BBs that spans a ``length_mm`` bar: ``bbs`` (1-based, as the report numbers them) when given,
    else the one pair whose distance is within ``tolerance`` of the length (an error names the pairs otherwise)."""
    if not np.isfinite(length_mm) or length_mm <= 0:
        raise ScaleBarError(f"scale bar length {length_mm!r} mm: must be a positive number of millimetres")
    k = xyz.shape[0]
    if bbs is not None:
        i, j = (int(b) - 1 for b in bbs)
        if not (0 <= i < k and 0 <= j < k and i != j):
            raise ScaleBarError(f"scale bar BBs {bbs[0]},{bbs[1]}: give two different BB numbers from 1 to {k}")
        return ScaleBar((min(i, j), max(i, j)), float(length_mm), float(np.linalg.norm(xyz[i] - xyz[j])))
    pairs = [(i, j, float(np.linalg.norm(xyz[i] - xyz[j]))) for i, j in combinations(range(k), 2)]
    near = [p for p in pairs if abs(p[2] / length_mm - 1.0) <= tolerance]
    if len(near) == 1:
        i, j, d = near[0]
        return ScaleBar((i, j), float(length_mm), d)
    closest = sorted(pairs, key=lambda p: abs(p[2] - length_mm))[:4]
    listed = ", ".join(f"{i + 1}-{j + 1} at {d:.1f} mm" for i, j, d in (near or closest))
    why = f"{len(near)} pairs of BBs are" if near else "no pair of BBs is"
    raise ScaleBarError(
        f"scale bar of {length_mm:g} mm: {why} within {100 * tolerance:g} % of it ({listed}); "
        "name the pair with the BB numbers of the report (--scale-bar-bbs I,J)"
    )


def rescaled_views(geometry: ViewGeometry, factor: float) -> ViewGeometry:
    """The same views with the object frame ``factor`` times larger: every source moves away from the object's
    origin by ``factor``, each detector moves with its source, and no pixel of a scaled point changes."""
    vec = geometry.vectors.copy()
    shift = (factor - 1.0) * vec[:, 0:3]
    vec[:, 0:3] += shift
    vec[:, 3:6] += shift
    return geometry.with_vectors(vec)


__all__ = ["DEFAULT_TOLERANCE", "ScaleBar", "ScaleBarError", "find_scale_bar", "rescaled_views"]
