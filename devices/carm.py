"""Robotic C-arm driver: the frame protocol plus navigation-point motion (``tcp://host:port``).

Angles: primary = LAO/RAO = ``theta``, secondary = CRAN/CAUD = ``phi`` of ``geometry.md``, in
degrees at this edge. Programs (:mod:`devices.carm_program`) are loaded point by point and
played back; ``stop()`` halts the arm on a connection of its own.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Mapping
from typing import Any

from devices.base import AxisInfo, DeviceInfo, Status
from devices.carm_program import CArmLimits, NavProgram
from devices.detector import Detector
from devices.errors import DeviceError, DeviceTimeoutError, OutOfLimitsError
from devices.frame_protocol import CARM_PORT, Frame


class CArm(Detector):
    """Driver of a robotic C-arm speaking the frame protocol plus navigation commands (``tcp://host:port``)."""

    OPTIONS = Detector.OPTIONS | {"stall_s"}
    default_port = CARM_PORT
    kind = "C-arm"

    def __init__(self, name: str = "carm", uri: str = "tcp://127.0.0.1:5040", **options: Any) -> None:
        stall_s = options.pop("stall_s", None)
        super().__init__(name, uri, **options)
        self.stall_s = float(stall_s if stall_s is not None else self._extra.pop("stall_s", 2.0))
        self._limits: CArmLimits | None = None

    async def connect(self) -> None:
        """Connect, read the limits, arm the panel for software triggers."""
        await super().connect()
        self._limits = CArmLimits.from_json(json.loads(await self._l().command("LIMITS?")))
        if not self.monitor:
            await self.arm()

    async def describe(self) -> DeviceInfo:
        """Model, serial, panel and the two angle axes with their ranges."""
        info = await super().describe()
        lim = self.limits_now
        axes = (AxisInfo("primary", "deg", *lim.primary_deg), AxisInfo("secondary", "deg", *lim.secondary_deg))
        return DeviceInfo(
            info.name, info.model, info.serial, info.firmware, axes, info.uri, {**info.extra, "limits": lim.to_json()}
        )

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
        self._check_interlock("move")
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
            report(
                fraction=len(frames) / n_frames,
                message=f"frame {len(frames)}/{n_frames}",
                current={"point": float(frame.meta.get("point", -1))},
            )
        return frames
