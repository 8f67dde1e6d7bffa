"""Per-frame positioner angles of a classic XA/XRF run, from its first-frame angles and its angle increments.

DICOM (PS3.3 C.8.7.5.1.3) lets the increments hold one value (the average change per frame), or one value per frame:
offsets from the first frame's angle, or absolute angles with the first-frame angles set to 0. Vendors also write one
value per frame as the change from the previous frame (steps), or absolute angles beside a non-zero first-frame
angle. The values tell which: a reading must put the first frame at the first-frame angle, stay within one turn,
and move the C-arm smoothly; when two readings still fit, the user chooses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

AngleIncrements = Literal["auto", "offsets", "steps", "absolute"]
ANGLE_INCREMENTS: tuple[AngleIncrements, ...] = ("auto", "offsets", "steps", "absolute")
READINGS = {
    "offsets": "offsets from the first frame's angle (DICOM's reading)",
    "steps": "changes from the previous frame (steps)",
    "absolute": "absolute angles",
}
SAME_DEG = 0.01  # angles closer than this are the same angle
ONE_TURN_DEG = 360.0  # no C-arm turns further than this in one run


class AngleReadingError(ValueError):
    """The increments cannot be read as asked, or fit more than one reading: the message says which and why."""


@dataclass(frozen=True)
class FrameAngles:
    """A run's per-frame primary and secondary angles (degrees) and how its increments were read."""

    primary_deg: np.ndarray
    secondary_deg: np.ndarray
    reading: str  # one of READINGS, or "average" for a single value
    why: str


def _read(reading: str, start: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Angles (frames x axes) from first-frame angles ``start`` and increments ``values`` read as ``reading``."""
    if reading == "offsets":
        return start + values
    if reading == "absolute":
        return values.copy()
    steps = values.copy()
    steps[0] = 0.0  # the first frame is at the first-frame angle, whatever its own step says
    return start + np.cumsum(steps, axis=0)


def _first_frame_fits(reading: str, start: np.ndarray, values: np.ndarray) -> bool:
    """Whether ``reading`` puts the first frame at the first-frame angle (steps always does); first-frame angles of
    0 beside absolute angles are DICOM's placeholder, not the first frame's angle."""
    if reading != "steps" and not start.any():
        return True
    first = _read(reading, start, values)[0]
    return bool(np.all(np.abs(first - start) <= SAME_DEG))


def roughness(angles: np.ndarray) -> float:
    """How unevenly a run moves: the median change of the per-frame motion over the median motion (0 for a C-arm at
    constant speed, about 1 and more for noise or a run that jumps once and stands); infinite for a run that stands."""
    step = np.linalg.norm(np.diff(angles, axis=0), axis=1)
    if angles.shape[0] < 3 or np.median(step) <= SAME_DEG / 10:
        return float("inf")
    jerk = np.linalg.norm(np.diff(angles, 2, axis=0), axis=1)
    return float(np.median(jerk) / np.median(step))


def _describe(reading: str, angles: np.ndarray) -> str:
    step = np.linalg.norm(np.diff(angles, axis=0), axis=1)
    span = np.ptp(angles, axis=0)
    return (
        f"read as {READINGS[reading]}: {np.median(step):.3g} deg per frame, primary spans {span[0]:.4g} deg, "
        f"secondary {span[1]:.4g} deg"
    )


def frame_angles(
    start_deg: tuple[float, float], increments_deg: tuple[np.ndarray, np.ndarray], n: int, choice: AngleIncrements
) -> FrameAngles:
    """The ``n`` frames' (primary, secondary) angles from the first-frame angles and the increments (each of one or
    ``n`` values), read as ``choice`` or, for "auto", as the values show; AngleReadingError when they cannot be."""
    if choice not in ANGLE_INCREMENTS:
        raise AngleReadingError(f"angle increments {choice!r}: choose one of {', '.join(ANGLE_INCREMENTS)}")
    start = np.asarray(start_deg, dtype=float)
    if all(v.size == 1 for v in increments_deg) and n > 1:
        per_frame = np.array([float(v[0]) for v in increments_deg])
        if choice in ("offsets", "absolute"):
            raise AngleReadingError(
                f"the angle increments hold one value each, which DICOM defines as the average change per frame; "
                f"they cannot be read as {choice}: choose auto or steps"
            )
        angles = start + np.arange(n)[:, None] * per_frame
        why = f"one value each: the average change per frame ({per_frame[0]:.4g} and {per_frame[1]:.4g} deg)"
        return FrameAngles(angles[:, 0], angles[:, 1], "average", why)
    values = np.stack([np.broadcast_to(v, (n,)) for v in increments_deg], axis=1).astype(float)
    if choice != "auto":
        angles = _read(choice, start, values)
        if not _first_frame_fits(choice, start, values):
            raise AngleReadingError(
                f"read as {READINGS[choice]}, the first frame's angles {_pair(angles[0])} differ from the run's "
                f"first-frame angles {_pair(start)}: the increments are not {choice}; try auto"
            )
        return FrameAngles(angles[:, 0], angles[:, 1], choice, f"{_describe(choice, angles)}, as chosen")
    readings, ruled_out = {}, []
    for r in READINGS:
        angles = _read(r, start, values)
        if not _first_frame_fits(r, start, values):
            ruled_out.append(f"as {r} the first frame would be at {_pair(angles[0])}")
        elif np.any(np.ptp(angles, axis=0) > ONE_TURN_DEG):
            ruled_out.append(f"as {r} the C-arm would turn {np.ptp(angles, axis=0).max():.4g} deg")
        else:
            readings[r] = angles
    if not readings:
        raise AngleReadingError(
            f"the angle increments fit none of offsets, steps or absolute angles ({'; '.join(ruled_out)}): check "
            "the run's PositionerPrimaryAngle and its increments"
        )
    distinct: dict[str, np.ndarray] = {}
    placeholder = not start.any() and bool(values[0].any())  # absolute angles beside zeros, as DICOM's note allows
    order = ("absolute", "offsets", "steps") if placeholder else ("offsets", "absolute", "steps")
    for r in order:  # the first of readings that give the same angles names them
        if r in readings and not any(np.allclose(readings[r], a, atol=SAME_DEG) for a in distinct.values()):
            distinct[r] = readings[r]
    ranked = sorted(distinct, key=lambda r: roughness(distinct[r]))
    best = ranked[0]
    if len(ranked) > 1:
        first, second = roughness(distinct[best]), roughness(distinct[ranked[1]])
        if second <= max(3.0 * first, 0.05):
            raise AngleReadingError(
                f"the angle increments fit two readings that give different angles: {READINGS[best]} and "
                f"{READINGS[ranked[1]]}; choose one (--angle-increments on the command line, angle_increments in the API)"
            )
    why = _describe(best, distinct[best])
    if roughness(distinct[best]) == float("inf"):
        why += "; the views do not move"
    why += "".join(f"; {note}" for note in ruled_out)
    for other in ranked[1:]:
        moved = roughness(distinct[other])
        why += f"; as {other} the C-arm would " + (
            "not move" if moved == float("inf") else f"move unevenly (roughness {moved:.2g})"
        )
    return FrameAngles(distinct[best][:, 0], distinct[best][:, 1], best, why)


def _pair(angles: np.ndarray) -> str:
    return f"({angles[0]:.4g}, {angles[1]:.4g}) deg"
