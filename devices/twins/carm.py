"""Robotic C-arm twin: plays navigation programs back with systematic errors and images a fixed object.

Source and detector move, the object stays (C-arm geometry). Each frame is rendered with
``ViewGeometry.from_carm`` at the TRUE pose, which differs from the commanded (and read-back)
angles ``theta_c, phi_c`` (rad) by:

* primary offset: ``theta = theta_c + primary_offset``
* tilt sag (gravity): ``phi = phi_c - sag * cos(theta_c) * cos(phi_c)``
* isocenter drift: ``shift = drift * (sin theta_c, 0.5 sin 2 theta_c, 0.5 (1 - cos theta_c)) + N(0, noise^2)`` mm
* in-plane panel rotation: ``eta`` (constant)

The true view of every frame travels with it (``meta['truth_vectors']``). Besides the detector
commands (see :mod:`devices.twins.detector`) it serves ``LIMITS?`` (JSON), ``PROG CLEAR``,
``PROG ADD <csv fields>``, ``PROG?``, ``GOTO i``, ``MOVE p s``, ``POS?`` (p s moving point),
``ONT?``, ``STOP``, ``RUN`` and ``RUN?`` (running point n_acquire frames_rendering).
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from typing import Any

import numpy as np

from devices.carm_program import CArmLimits, NavPoint
from devices.frame_protocol import ERR_BAD_ARG, ERR_LIMITS, ERR_NOT_ARMED
from devices.twins.detector import DetectorTwin
from devices.twins.line_server import CommandError, int_arg
from devices.twins.world import SimWorld, get_world
from orbitct.geometry import ViewGeometry


class CArmTwin(DetectorTwin):
    """Simulated robotic C-arm with a flat panel, navigation-point playback and systematic pose errors."""

    model = "orbitct SimCArm"
    serial = "CA-0001"
    firmware = "1.0"

    def __init__(
        self,
        world: SimWorld | None = None,
        *,
        limits: CArmLimits | None = None,
        sag_deg: float = 0.8,
        drift_mm: float = 2.0,
        eta_deg: float = 0.5,
        primary_offset_deg: float = 0.3,
        noise_mm: float = 0.1,
        time_scale: float = 1.0,
        phantom: Any = "B",
        **panel: Any,
    ) -> None:
        super().__init__(world if world is not None else get_world("carm"), phantom=phantom, **panel)
        self.limits = limits or CArmLimits()
        self.sag = math.radians(float(sag_deg))
        self.drift_mm = float(drift_mm)
        self.eta = math.radians(float(eta_deg))
        self.primary_offset = math.radians(float(primary_offset_deg))
        self.noise_mm = float(noise_mm)
        self.time_scale = float(time_scale)  # simulated seconds per wall-clock second
        self.program: list[NavPoint] = []
        self.primary_deg = 0.0
        self.secondary_deg = 0.0
        self.point = -1
        self.truth: list[np.ndarray] = []  # true view vectors of every projection, in order
        self._motion: asyncio.Task[None] | None = None
        self._run: asyncio.Task[None] | None = None
        self.armed = True
        self.stuck = False  # hazard on request: moves report "moving" but the arm does not advance

    # ------------------------------------------------------------- geometry
    def true_view(self) -> ViewGeometry:
        """True view now: commanded angles plus the systematic errors (source and detector move)."""
        th_c, ph_c = math.radians(self.primary_deg), math.radians(self.secondary_deg)
        theta = th_c + self.primary_offset
        phi = ph_c - self.sag * math.cos(th_c) * math.cos(ph_c)
        shift = self.drift_mm * np.array([math.sin(th_c), 0.5 * math.sin(2 * th_c), 0.5 * (1 - math.cos(th_c))])
        shift = (
            shift + np.asarray(self.limits.isocenter_mm) + self.rng.normal(0.0, self.noise_mm, 3) * (self.noise_mm > 0)
        )
        view = ViewGeometry.from_carm(theta, phi, self.sad_mm, self.sdd_mm, self.geometry, eta=self.eta, shift=shift)
        self.truth.append(view.vectors[0].copy())
        return view

    def frame_meta(self) -> dict[str, Any]:
        """Program point and read-back angles of the frame."""
        return {"point": self.point, "primary_deg": self.primary_deg, "secondary_deg": self.secondary_deg}

    async def started(self) -> None:
        """Warm the renderer; no generator watch (the C-arm exposes on its own triggers)."""
        await asyncio.get_running_loop().run_in_executor(None, self.warm_up)

    # --------------------------------------------------------------- motion
    @property
    def moving(self) -> bool:
        """Whether a move is in progress."""
        return self._motion is not None and not self._motion.done()

    def _start_move(self, p: float, s: float, speed_deg_s: float) -> asyncio.Task[None]:
        why = self.limits.check_point(p, s)
        if why:
            raise CommandError(ERR_LIMITS, why)
        if self.moving:
            assert self._motion is not None
            self._motion.cancel()
        self._motion = asyncio.ensure_future(self._travel(p, s, min(speed_deg_s, self.limits.max_speed_deg_s)))
        return self._motion

    async def _travel(self, p: float, s: float, speed: float) -> None:
        p0, s0 = self.primary_deg, self.secondary_deg
        duration = max(abs(p - p0), abs(s - s0)) / max(speed, 1e-9) / self.time_scale
        t0 = time.monotonic()
        while self.stuck:
            await asyncio.sleep(0.01)
        while True:
            f = 1.0 if duration <= 0 else min(1.0, (time.monotonic() - t0) / duration)
            self.primary_deg, self.secondary_deg = p0 + f * (p - p0), s0 + f * (s - s0)
            if f >= 1.0:
                return
            await asyncio.sleep(min(0.01, duration / 20))

    def cmd_limits_q(self, args: list[str]) -> str:
        """``LIMITS?``: the C-arm limits as JSON."""
        return json.dumps(self.limits.to_json())

    def cmd_prog(self, args: list[str]) -> str:
        """``PROG CLEAR`` or ``PROG ADD <csv fields>`` (checked against the limits); a new program starts the frames'
        noise afresh (:meth:`restart_noise`)."""
        if args[:1] == ["CLEAR"]:
            self.program = []
            self.restart_noise()
            return ""
        if args[:1] == ["ADD"]:
            try:
                pt = NavPoint.from_fields(args[1:])
            except ValueError as exc:
                raise CommandError(ERR_BAD_ARG, f"PROG ADD: {exc}") from None
            if pt.index != len(self.program):
                raise CommandError(ERR_BAD_ARG, f"PROG ADD: expected point index {len(self.program)}, got {pt.index}")
            why = self.limits.check_point(pt.primary_deg, pt.secondary_deg)
            if why:
                raise CommandError(ERR_LIMITS, f"point {pt.index}: {why}")
            self.program.append(pt)
            return ""
        raise CommandError(ERR_BAD_ARG, "PROG takes CLEAR or ADD <fields>")

    def cmd_prog_q(self, args: list[str]) -> str:
        """``PROG?``: number of points loaded."""
        return str(len(self.program))

    def cmd_goto(self, args: list[str]) -> str:
        """``GOTO i``: move to program point i."""
        i = int_arg(args, 0)
        if not 0 <= i < len(self.program):
            raise CommandError(ERR_BAD_ARG, f"GOTO: point {i} not in the program (0..{len(self.program) - 1})")
        pt = self.program[i]
        self._start_move(pt.primary_deg, pt.secondary_deg, pt.speed_deg_s)
        self.point = i
        return ""

    def cmd_move(self, args: list[str]) -> str:
        """``MOVE p s [speed]``: move to angles (deg)."""
        try:
            p, s = float(args[0]), float(args[1])
            speed = float(args[2]) if len(args) > 2 else self.limits.max_speed_deg_s
        except (IndexError, ValueError):
            raise CommandError(ERR_BAD_ARG, "MOVE takes <primary_deg> <secondary_deg> [speed_deg_s]") from None
        self._start_move(p, s, speed)
        self.point = -1
        return ""

    def cmd_pos_q(self, args: list[str]) -> str:
        """``POS?``: primary secondary moving point."""
        return f"{self.primary_deg:.6f} {self.secondary_deg:.6f} {int(self.moving)} {self.point}"

    def cmd_ont_q(self, args: list[str]) -> str:
        """``ONT?``: 1 when not moving."""
        return "0" if self.moving else "1"

    def cmd_stop(self, args: list[str]) -> str:
        """``STOP``: halt the arm and any program run."""
        for task in (self._run, self._motion):
            if task is not None:
                task.cancel()
        return ""

    # ------------------------------------------------------------- playback
    def cmd_run(self, args: list[str]) -> str:
        """``RUN``: play the loaded program in the background."""
        if not self.program:
            raise CommandError(ERR_NOT_ARMED, "RUN: no program loaded")
        if self._run is not None and not self._run.done():
            raise CommandError(ERR_NOT_ARMED, "RUN: a program is already running")
        self.clear_frames()
        self._run = self.spawn(self._play())
        return ""

    def cmd_run_q(self, args: list[str]) -> str:
        """``RUN?``: running point n_acquire frames_rendering."""
        running = self._run is not None and not self._run.done()
        return f"{int(running)} {self.point} {sum(p.acquire for p in self.program)} {self.rendering}"

    async def _play(self) -> None:
        for i, pt in enumerate(self.program):
            self.point = i
            await self._start_move(pt.primary_deg, pt.secondary_deg, pt.speed_deg_s)
            if pt.acquire:
                self.start_frame("projection", *self._settings())
