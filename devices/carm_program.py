"""C-arm navigation-point programs: what the C-arm driver and its twin share (orbit -> CSV/JSON program).

Angles: primary = LAO/RAO = ``theta``, secondary = CRAN/CAUD = ``phi`` of ``geometry.md``, in
degrees at this edge. A program is an ordered list of :class:`NavPoint`; points with
``acquire = 1`` take one frame (one per orbit frame, in orbit order); points with
``acquire = 0`` are inserted only to bridge the jump between orbit segments in steps no larger
than the C-arm's maximum step.

CSV (UTF-8, ``#`` comment lines first, then a header row and one row per point)::

    # orbitct C-arm navigation program v1
    # orbit: sawtooth {"n_frames": 500, ...}
    # limits: {"primary_deg": [-185, 185], "secondary_deg": [-50, 50], "max_step_deg": 5.0, ...}
    index,segment,primary_deg,secondary_deg,iso_x_mm,iso_y_mm,iso_z_mm,speed_deg_s,acquire
    0,0,-90.000000,0.000000,0.000,0.000,0.000,20.000,1

JSON: ``{"format": "orbitct-carm-navigation", "version": 1, "orbit": {...}, "limits": {...},
"points": [{"index": 0, "segment": 0, "primary_deg": ..., "secondary_deg": ...,
"isocenter_mm": [x, y, z], "speed_deg_s": ..., "acquire": true}, ...]}``.

The C-arm speaks the frame protocol (:mod:`devices.frame_protocol`) plus ``LIMITS?``,
``PROG CLEAR``, ``PROG ADD <fields of a CSV row>``, ``PROG?``, ``GOTO i``, ``MOVE p s [speed]``,
``POS?``, ``ONT?``, ``STOP``, ``RUN``, ``RUN?``.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

CSV_FIELDS = (
    "index",
    "segment",
    "primary_deg",
    "secondary_deg",
    "iso_x_mm",
    "iso_y_mm",
    "iso_z_mm",
    "speed_deg_s",
    "acquire",
)


class InfeasibleOrbitError(ValueError):
    """The orbit cannot be driven by this C-arm; ``index`` is the first offending orbit frame."""

    def __init__(self, index: int, message: str) -> None:
        super().__init__(message)
        self.index = index


class ProgramFileError(ValueError):
    """A navigation-program file that cannot be read; the message names file, line and field."""


@dataclass(frozen=True)
class CArmLimits:
    """Angle ranges (deg), largest step between consecutive points (deg), top speed (deg/s), isocenter (mm)."""

    primary_deg: tuple[float, float] = (-185.0, 185.0)
    secondary_deg: tuple[float, float] = (-50.0, 50.0)
    max_step_deg: float = 5.0
    max_speed_deg_s: float = 30.0
    isocenter_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def check_point(self, primary_deg: float, secondary_deg: float) -> str:
        """Why a pose is out of range ('' when it is fine)."""
        lo, hi = self.primary_deg
        if not lo <= primary_deg <= hi:
            return f"primary angle {primary_deg:.3f} deg is outside the C-arm range [{lo:g}, {hi:g}]"
        lo, hi = self.secondary_deg
        if not lo <= secondary_deg <= hi:
            return f"secondary angle {secondary_deg:.3f} deg is outside the C-arm range [{lo:g}, {hi:g}]"
        return ""

    def to_json(self) -> dict[str, Any]:
        """Plain values for the program files."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> CArmLimits:
        """Inverse of :meth:`to_json`."""
        values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else float(v) for k, v in d.items()}
        return cls(**values)


@dataclass(frozen=True)
class NavPoint:
    """One navigation point of a C-arm program."""

    index: int
    segment: int
    primary_deg: float
    secondary_deg: float
    isocenter_mm: tuple[float, float, float]
    speed_deg_s: float
    acquire: bool = True

    def csv_row(self) -> list[str]:
        """The point as CSV fields in :data:`CSV_FIELDS` order."""
        x, y, z = self.isocenter_mm
        return [
            str(self.index),
            str(self.segment),
            f"{self.primary_deg:.6f}",
            f"{self.secondary_deg:.6f}",
            f"{x:.4f}",
            f"{y:.4f}",
            f"{z:.4f}",
            f"{self.speed_deg_s:.4f}",
            str(int(self.acquire)),
        ]

    @classmethod
    def from_fields(cls, fields: Sequence[str | float]) -> NavPoint:
        """Parse :data:`CSV_FIELDS`-ordered text fields (ValueError on bad input)."""
        if len(fields) != len(CSV_FIELDS):
            raise ValueError(f"expected {len(CSV_FIELDS)} fields ({', '.join(CSV_FIELDS)}), got {len(fields)}")
        f = [float(v) for v in fields]
        if not all(math.isfinite(v) for v in f):
            raise ValueError("fields must be finite numbers")
        if f[8] not in (0.0, 1.0):
            raise ValueError(f"acquire must be 0 or 1, got {fields[8]!r}")
        return cls(int(f[0]), int(f[1]), f[2], f[3], (f[4], f[5], f[6]), f[7], bool(f[8]))


@dataclass(frozen=True)
class NavProgram:
    """An ordered navigation-point program with the limits it was checked against."""

    points: tuple[NavPoint, ...]
    limits: CArmLimits = field(default_factory=CArmLimits)
    orbit: dict[str, Any] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        """Number of points that take a frame."""
        return sum(p.acquire for p in self.points)

    def __len__(self) -> int:
        return len(self.points)

    def to_csv(self) -> str:
        """The documented CSV text."""
        out = io.StringIO()
        out.write("# orbitct C-arm navigation program v1\n")
        out.write(f"# orbit: {json.dumps(self.orbit)}\n# limits: {json.dumps(self.limits.to_json())}\n")
        w = csv.writer(out, lineterminator="\n")
        w.writerow(CSV_FIELDS)
        for p in self.points:
            w.writerow(p.csv_row())
        return out.getvalue()

    def to_json(self) -> dict[str, Any]:
        """The documented JSON document."""
        pts = [
            {**{k: v for k, v in asdict(p).items() if k != "isocenter_mm"}, "isocenter_mm": list(p.isocenter_mm)}
            for p in self.points
        ]
        return {
            "format": "orbitct-carm-navigation",
            "version": 1,
            "orbit": self.orbit,
            "limits": self.limits.to_json(),
            "points": pts,
        }

    def write(self, path: str | Path) -> Path:
        """Write CSV (``.csv``) or JSON (``.json``) by suffix."""
        p = Path(path)
        if p.suffix.lower() == ".csv":
            p.write_text(self.to_csv())
        elif p.suffix.lower() == ".json":
            p.write_text(json.dumps(self.to_json(), indent=1))
        else:
            raise ProgramFileError(f"{p}: program files end in .csv or .json")
        return p

    @classmethod
    def read(cls, path: str | Path) -> NavProgram:
        """Read a CSV or JSON program written by :meth:`write` (or by hand in the same format)."""
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise ProgramFileError(f"{p}: cannot read ({exc.strerror})") from None
        return cls._from_json_text(p, text) if p.suffix.lower() == ".json" else cls._from_csv_text(p, text)

    @classmethod
    def _from_csv_text(cls, p: Path, text: str) -> NavProgram:
        meta: dict[str, Any] = {}
        rows: list[tuple[int, list[str]]] = []
        for n, line in enumerate(text.splitlines(), 1):
            if line.startswith("#"):
                key, _, value = line[1:].partition(":")
                if key.strip() in ("orbit", "limits"):
                    try:
                        meta[key.strip()] = json.loads(value)
                    except json.JSONDecodeError:
                        raise ProgramFileError(f"{p}:{n}: '# {key.strip()}:' is not JSON") from None
            elif line.strip():
                rows.append((n, next(csv.reader([line]))))
        if not rows or tuple(c.strip() for c in rows[0][1]) != CSV_FIELDS:
            raise ProgramFileError(f"{p}: header row must be {','.join(CSV_FIELDS)}")
        points = []
        for n, fields in rows[1:]:
            try:
                points.append(NavPoint.from_fields(fields))
            except ValueError as exc:
                raise ProgramFileError(f"{p}:{n}: {exc}") from None
        return cls._checked(p, points, meta)

    @classmethod
    def _from_json_text(cls, p: Path, text: str) -> NavProgram:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ProgramFileError(f"{p}: not JSON ({exc.msg} at line {exc.lineno})") from None
        if not isinstance(doc, dict) or doc.get("format") != "orbitct-carm-navigation":
            raise ProgramFileError(f"{p}: 'format' must be 'orbitct-carm-navigation'")
        points = []
        for i, d in enumerate(doc.get("points", [])):
            try:
                iso = d["isocenter_mm"]
                points.append(
                    NavPoint.from_fields(
                        [
                            d["index"],
                            d["segment"],
                            d["primary_deg"],
                            d["secondary_deg"],
                            *iso,
                            d["speed_deg_s"],
                            int(d["acquire"]),
                        ]
                    )
                )
            except (KeyError, TypeError, ValueError) as exc:
                raise ProgramFileError(f"{p}: points[{i}]: {exc!s} (fields: {', '.join(CSV_FIELDS)})") from None
        return cls._checked(p, points, doc)

    @classmethod
    def _checked(cls, p: Path, points: list[NavPoint], meta: Mapping[str, Any]) -> NavProgram:
        if [pt.index for pt in points] != list(range(len(points))):
            raise ProgramFileError(f"{p}: point indices must run 0, 1, 2, ... in order")
        try:
            limits = CArmLimits.from_json(meta["limits"]) if "limits" in meta else CArmLimits()
        except (TypeError, ValueError) as exc:
            raise ProgramFileError(f"{p}: bad limits ({exc})") from None
        return cls(tuple(points), limits, dict(meta.get("orbit", {})))


def export_program(orbit: Any, limits: CArmLimits = CArmLimits(), *, speed_deg_s: float = 20.0) -> NavProgram:
    """Navigation points for ``orbit`` (an :class:`orbitct.orbits.Orbit`); InfeasibleOrbitError names the first bad frame."""
    if not 0 < speed_deg_s <= limits.max_speed_deg_s:
        raise ValueError(f"speed_deg_s must be in (0, {limits.max_speed_deg_s:g}], got {speed_deg_s:g}")
    theta, phi = np.degrees(np.asarray(orbit.theta, float)), np.degrees(np.asarray(orbit.phi, float))
    segment = np.asarray(getattr(orbit, "segment", np.zeros(theta.shape, int)), int)
    iso = tuple(float(v) for v in limits.isocenter_mm)
    points: list[NavPoint] = []

    def add(p: float, s: float, seg: int, acquire: bool) -> None:
        points.append(NavPoint(len(points), seg, float(p), float(s), iso, float(speed_deg_s), acquire))  # type: ignore[arg-type]

    for i in range(theta.shape[0]):
        why = limits.check_point(theta[i], phi[i])
        if why:
            raise InfeasibleOrbitError(i, f"orbit frame {i}: {why}")
        if i > 0:
            step = max(abs(theta[i] - theta[i - 1]), abs(phi[i] - phi[i - 1]))
            if segment[i] == segment[i - 1] and step > limits.max_step_deg + 1e-9:
                raise InfeasibleOrbitError(
                    i,
                    f"orbit frame {i}: step of {step:.3f} deg from frame {i - 1} exceeds the C-arm's maximum step {limits.max_step_deg:g} deg",
                )
            if segment[i] != segment[i - 1] and step > limits.max_step_deg:
                n = int(math.ceil(step / limits.max_step_deg))
                for k in range(1, n):  # bridge between segments, no frames
                    f = k / n
                    add(
                        theta[i - 1] + f * (theta[i] - theta[i - 1]),
                        phi[i - 1] + f * (phi[i] - phi[i - 1]),
                        int(segment[i]),
                        False,
                    )
        add(theta[i], phi[i], int(segment[i]), True)
    name = getattr(orbit, "name", "orbit")
    params = getattr(orbit, "params", {})
    return NavProgram(tuple(points), limits, {"name": name, "params": json.loads(json.dumps(params, default=str))})
