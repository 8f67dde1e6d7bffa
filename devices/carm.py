"""Robotic C-arm: orbit -> navigation-point program (CSV/JSON), and the C-arm driver (frame protocol + motion).

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

C-arm line commands (besides the detector's, see :mod:`devices.twins.carm`): ``LIMITS?``,
``PROG CLEAR``, ``PROG ADD <fields of a CSV row>``, ``PROG?``, ``GOTO i``, ``MOVE p s [speed]``,
``POS?``, ``ONT?``, ``STOP``, ``RUN``, ``RUN?``.
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from devices.base import DeviceInfo, Status
from devices.detector import Detector, Frame
from devices.errors import DeviceError, DeviceTimeoutError, OutOfLimitsError

CARM_PORT = 5040
CSV_FIELDS = ("index", "segment", "primary_deg", "secondary_deg", "iso_x_mm", "iso_y_mm", "iso_z_mm", "speed_deg_s", "acquire")


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
    def from_json(cls, d: Mapping[str, Any]) -> "CArmLimits":
        """Inverse of :meth:`to_json`."""
        return cls(**{k: tuple(v) if isinstance(v, list) else float(v) for k, v in d.items()})


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
        return [str(self.index), str(self.segment), f"{self.primary_deg:.6f}", f"{self.secondary_deg:.6f}",
                f"{x:.4f}", f"{y:.4f}", f"{z:.4f}", f"{self.speed_deg_s:.4f}", str(int(self.acquire))]

    @classmethod
    def from_fields(cls, fields: Sequence[str]) -> "NavPoint":
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
        pts = [{**{k: v for k, v in asdict(p).items() if k != "isocenter_mm"}, "isocenter_mm": list(p.isocenter_mm)} for p in self.points]
        return {"format": "orbitct-carm-navigation", "version": 1, "orbit": self.orbit, "limits": self.limits.to_json(), "points": pts}

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
    def read(cls, path: str | Path) -> "NavProgram":
        """Read a CSV or JSON program written by :meth:`write` (or by hand in the same format)."""
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise ProgramFileError(f"{p}: cannot read ({exc.strerror})") from None
        return cls._from_json_text(p, text) if p.suffix.lower() == ".json" else cls._from_csv_text(p, text)

    @classmethod
    def _from_csv_text(cls, p: Path, text: str) -> "NavProgram":
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
    def _from_json_text(cls, p: Path, text: str) -> "NavProgram":
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
                points.append(NavPoint.from_fields([d["index"], d["segment"], d["primary_deg"], d["secondary_deg"], *iso, d["speed_deg_s"], int(d["acquire"])]))
            except (KeyError, TypeError, ValueError) as exc:
                raise ProgramFileError(f"{p}: points[{i}]: {exc!s} (fields: {', '.join(CSV_FIELDS)})") from None
        return cls._checked(p, points, doc)

    @classmethod
    def _checked(cls, p: Path, points: list[NavPoint], meta: Mapping[str, Any]) -> "NavProgram":
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
                    i, f"orbit frame {i}: step of {step:.3f} deg from frame {i - 1} exceeds the C-arm's maximum step {limits.max_step_deg:g} deg"
                )
            if segment[i] != segment[i - 1] and step > limits.max_step_deg:
                n = int(math.ceil(step / limits.max_step_deg))
                for k in range(1, n):  # bridge between segments, no frames
                    f = k / n
                    add(theta[i - 1] + f * (theta[i] - theta[i - 1]), phi[i - 1] + f * (phi[i] - phi[i - 1]), int(segment[i]), False)
        add(theta[i], phi[i], int(segment[i]), True)
    name = getattr(orbit, "name", "orbit")
    params = getattr(orbit, "params", {})
    return NavProgram(tuple(points), limits, {"name": name, "params": json.loads(json.dumps(params, default=str))})


class CArm(Detector):
    """Driver of a robotic C-arm speaking the frame protocol plus navigation commands (``sim://`` or ``tcp://``)."""

    OPTIONS = Detector.OPTIONS | {"sag_deg", "drift_mm", "eta_deg", "primary_offset_deg", "noise_mm", "time_scale", "limits", "stall_s"}
    default_port = CARM_PORT
    kind = "C-arm"

    def __init__(self, name: str = "carm", uri: str = "sim://carm", **options: Any) -> None:
        options.setdefault("phantom", "B")
        stall_s = options.pop("stall_s", None)
        super().__init__(name, uri, **options)
        self.stall_s = float(stall_s if stall_s is not None else self._twin_options.pop("stall_s", 2.0))
        self._limits: CArmLimits | None = None

    def _make_twin(self) -> Any:
        from devices.twins.carm import CArmTwin
        from devices.twins.world import get_world

        return CArmTwin(get_world(self.endpoint.host or "carm"), **self._twin_options)

    async def connect(self) -> None:
        """Connect, read the limits, arm the panel for software triggers."""
        await super().connect()
        self._limits = CArmLimits.from_json(json.loads(await self._l().command("LIMITS?")))
        await self.arm()

    async def describe(self) -> DeviceInfo:
        """Model, serial, panel and the two angle axes with their ranges."""
        from devices.base import AxisInfo

        info = await super().describe()
        lim = self.limits_now
        axes = (AxisInfo("primary", "deg", *lim.primary_deg), AxisInfo("secondary", "deg", *lim.secondary_deg))
        return DeviceInfo(info.name, info.model, info.serial, info.firmware, axes, info.uri, {**info.extra, "limits": lim.to_json()})

    @property
    def limits_now(self) -> CArmLimits:
        """The C-arm's limits as reported at connect."""
        if self._limits is None:
            raise DeviceError(f"{self.name}: not connected")
        return self._limits

    async def limits(self) -> dict[str, tuple[float, float]]:
        """Angle ranges per axis (deg)."""
        return {"primary": self.limits_now.primary_deg, "secondary": self.limits_now.secondary_deg}

    async def position(self) -> dict[str, float]:
        """Encoded (read-back) angles in degrees."""
        p, s, _moving, _point = (await self._l().command("POS?")).split()
        return {"primary": float(p), "secondary": float(s)}

    async def on_target(self) -> bool:
        """Whether the last move has finished."""
        return (await self._l().command("ONT?")).strip() == "1"

    async def read(self) -> dict[str, Any]:
        """Panel state plus angles, moving flag and current program point."""
        out = await super().read()
        p, s, moving, point = (await self._l().command("POS?")).split()
        out.update(primary_deg=float(p), secondary_deg=float(s), moving=moving == "1", point=int(point))
        return out

    async def stop(self) -> None:
        """Halt the C-arm now (on a connection of its own, so it never waits behind a frame read)."""
        await self._l().urgent("STOP")

    async def load(self, program: NavProgram) -> None:
        """Send a program (checked against the C-arm's limits point by point; OutOfLimitsError names the point)."""
        lim = self.limits_now
        for pt in program.points:
            why = lim.check_point(pt.primary_deg, pt.secondary_deg)
            if why:
                raise OutOfLimitsError(f"{self.name}: program point {pt.index}: {why}; nothing loaded")
        await self._l().command("PROG CLEAR")
        for pt in program.points:
            await self._l().command("PROG ADD " + " ".join(pt.csv_row()))
        n = int(await self._l().command("PROG?"))
        if n != len(program.points):
            raise DeviceError(f"{self.name}: C-arm holds {n} points after loading {len(program.points)}")
        self._program = program

    async def _halting_on_cancel(self, action: Any) -> Any:
        """Run a motion coroutine; if it is cancelled (an abort), the C-arm is stopped before re-raising."""
        try:
            return await action
        except asyncio.CancelledError:
            try:
                await asyncio.shield(self.stop())
            except DeviceError:
                pass
            raise

    def move(self, targets: Mapping[str, float]) -> Status[None]:
        """Move to ``{'primary': deg, 'secondary': deg}`` (missing axes stay); ends on target. Cancelling stops the arm."""
        return Status(f"{self.name}.move", self._halting_on_cancel(self._move(dict(targets))))

    async def _move(self, targets: dict[str, float]) -> None:
        unknown = set(targets) - {"primary", "secondary"}
        if unknown:
            raise DeviceError(f"{self.name}: unknown axis {', '.join(sorted(unknown))}; axes are primary, secondary")
        pos = await self.position()
        p, s = targets.get("primary", pos["primary"]), targets.get("secondary", pos["secondary"])
        why = self.limits_now.check_point(p, s)
        if why:
            raise OutOfLimitsError(f"{self.name}: {why}; nothing moved")
        await self._l().command(f"MOVE {p:.6f} {s:.6f}", retry=False)
        await self._wait_on_target()

    def goto(self, index: int) -> Status[None]:
        """Move to program point ``index``; ends on target. Cancelling stops the arm."""
        return Status(f"{self.name}.goto", self._halting_on_cancel(self._goto(int(index))))

    async def _goto(self, index: int) -> None:
        await self._l().command(f"GOTO {index}", retry=False)
        await self._wait_on_target()

    async def _wait_on_target(self, poll_s: float = 0.005) -> None:
        """Poll until on target; a pose that stops changing for ``stall_s`` while moving is a stuck axis."""
        last, last_change = None, time.monotonic()
        while True:
            p, s, moving, _point = (await self._l().command("POS?")).split()
            if moving == "0":
                return
            if (p, s) != last:
                last, last_change = (p, s), time.monotonic()
            elif time.monotonic() - last_change > self.stall_s:
                await self.stop()
                raise DeviceTimeoutError(
                    f"{self.name}: C-arm stuck at primary {float(p):.3f} deg, secondary {float(s):.3f} deg "
                    f"(no progress for {self.stall_s:g} s); stopped, not retried"
                )
            await asyncio.sleep(poll_s)

    def expose(self) -> Status[Frame]:
        """One frame at the current pose (``frame.meta['truth_vectors']``: the true view)."""
        return self.trigger()

    def run(self) -> Status[list[Frame]]:
        """Play the loaded program; one frame per acquire point, in order; progress per frame. Cancelling stops the arm."""
        status: Status[list[Frame]]
        status = Status(f"{self.name}.run", self._halting_on_cancel(self._run(lambda **kw: status.report(**kw))))
        return status

    async def _run(self, report: Any) -> list[Frame]:
        total = int(await self._l().command("PROG?"))
        n_frames = int((await self._l().command("RUN?")).split()[2])
        if total == 0:
            raise DeviceError(f"{self.name}: no program loaded")
        await self._l().command("RUN", retry=False)
        frames: list[Frame] = []
        while len(frames) < n_frames:
            try:
                frame = await self.read_frame(timeout_s=1.0)
            except DeviceTimeoutError as exc:
                if "missing" in str(exc):
                    raise
                running, _point, _n, rendering = (await self._l().command("RUN?")).split()
                if running == "1" or rendering != "0":
                    continue
                try:  # the program ended and every frame is rendered: what it took is queued
                    frame = await self.read_frame(timeout_s=self.timeout_s)
                except DeviceTimeoutError:
                    raise DeviceTimeoutError(
                        f"{self.name}: program ended with {len(frames)} of {n_frames} frames; frame(s) missing, not re-taken"
                    ) from None
            frames.append(frame)
            report(fraction=len(frames) / n_frames, message=f"frame {len(frames)}/{n_frames}", current={"point": float(frame.meta.get("point", -1))})
        return frames
