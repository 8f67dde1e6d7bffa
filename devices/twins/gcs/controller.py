"""The GCS 2.0 command interpreter shared by the hexapod and rotation-stage twins.

A controller owns axes with soft limits (TMN?/TMX?), servo and reference state,
a :class:`~devices.twins.gcs.motion.LinearMotion`, and one error register per
connection (``ERR?`` reads and clears it). Kind-specific parts (velocity
commands, workspace, pivot, mechanical imperfections) live in subclasses.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from devices.gcs import errors as E
from devices.gcs.framing import BUSY, READY, axis_lines, format_value
from devices.twins.gcs.motion import LinearMotion
from devices.twins.runtime import TwinFaults


class Session:
    """One connection's view of the controller: its error register."""

    def __init__(self, name: str = "") -> None:
        self.name = name
        self.error = 0

    def fail(self, code: int) -> None:
        """Set the error register (the first error sticks until ``ERR?``, as on PI controllers)."""
        if self.error == 0:
            self.error = code


class GcsError(Exception):
    """Internal: a command failed with a GCS error code."""

    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


Reply = list[str] | None
Handler = Callable[[Session, list[str]], Reply]


class GcsController:
    """Base GCS 2.0 controller twin (axis bookkeeping and the common commands)."""

    idn = "(c)2026 orbitct twin, GCS controller, 0, 0.0.0"
    reference_pose: tuple[float, ...] = ()
    command_names: tuple[str, ...] = (
        "*IDN?",
        "CSV?",
        "ERR?",
        "HLP?",
        "SAI?",
        "SVO",
        "SVO?",
        "FRF",
        "FRF?",
        "MOV",
        "MOV?",
        "MVR",
        "POS?",
        "ONT?",
        "HLT",
        "STP",
        "TMN?",
        "TMX?",
        "#5",
        "#7",
        "#24",
    )

    def __init__(
        self,
        axes: Sequence[str],
        units: Sequence[str],
        low: Sequence[float],
        high: Sequence[float],
        start: Sequence[float],
        *,
        time_scale: float = 1.0,
        faults: TwinFaults | None = None,
    ) -> None:
        self.axes = tuple(axes)
        self.units = tuple(units)
        self.low = np.asarray(low, dtype=float)
        self.high = np.asarray(high, dtype=float)
        self.motion = LinearMotion(self.axes, start, time_scale=time_scale)
        self.servo = np.zeros(len(self.axes), dtype=bool)
        self.referenced = np.zeros(len(self.axes), dtype=bool)
        self.referencing = False
        self.faults = faults or TwinFaults()
        self.lock = threading.RLock()
        self._handlers: dict[str, Handler] = {}
        for name in self.command_names:
            method = "_" + name.replace("*", "").replace("?", "_q").replace("#", "char")
            self._handlers[name] = getattr(self, method.lower())

    # ----- public twin API (used by tests, the CLI and the in-process bench) -----
    def stick(self, axis: str, stuck: bool = True) -> None:
        """Make ``axis`` stuck (it will not move and never reports on target) or free it again."""
        with self.lock:
            self.motion.stuck[self._index(axis)] = stuck

    def update(self) -> None:
        """Advance bookkeeping (finish referencing) and publish the true state."""
        with self.lock:
            if self.referencing and not self.motion.moving().any():
                self.referencing = False
                self.referenced[:] = not self.motion.stuck.any()
            self.publish()

    def publish(self) -> None:
        """Write the true (mechanical) state to the simulated world (subclasses)."""

    def is_moving(self) -> bool:
        """Whether any axis is moving."""
        with self.lock:
            return bool(self.motion.moving().any())

    # ----- command dispatch -----
    def handle(self, session: Session, command: str) -> Reply:
        """Execute one command; returns reply lines (``None``: no reply, as for set commands)."""
        tokens = command.split()
        if not tokens:
            return None
        name = tokens[0].upper()
        if name == "SAI?" and len(tokens) == 2 and tokens[1].upper() == "ALL":
            tokens = tokens[:1]
        handler = self._handlers.get(name)
        if handler is None:
            session.fail(E.UNKNOWN_COMMAND)
            return None
        injected = self.faults.take_error(name)
        if injected:
            session.fail(injected)
            return None
        with self.lock:
            self.update()
            try:
                return handler(session, tokens[1:])
            except GcsError as err:
                session.fail(err.code)
                return None

    # ----- parsing helpers -----
    def _index(self, axis: str) -> int:
        try:
            return self.axes.index(axis.upper() if axis.upper() in self.axes else axis)
        except ValueError:
            raise GcsError(E.INVALID_AXIS) from None

    def _axis_list(self, args: list[str]) -> list[int]:
        return [self._index(a) for a in args] if args else list(range(len(self.axes)))

    def _pairs(self, args: list[str]) -> list[tuple[int, float]]:
        if not args:
            raise GcsError(E.PARAM_NR)
        if len(args) % 2:
            raise GcsError(E.PARAM_NR)
        out: list[tuple[int, float]] = []
        for a, v in zip(args[::2], args[1::2]):
            i = self._index(a)
            if any(i == j for j, _ in out):
                raise GcsError(22)
            try:
                out.append((i, float(v)))
            except ValueError:
                raise GcsError(E.PARAM_SYNTAX) from None
        return out

    def _axis_reply(self, idx: list[int], values: NDArray[np.generic] | Sequence[object]) -> list[str]:
        return axis_lines({self.axes[i]: values[i] for i in idx})  # type: ignore[misc]

    # ----- motion rules (subclasses refine) -----
    def within_limits(self, pose: NDArray[np.float64]) -> bool:
        """Whether a full target pose lies inside the soft limits (and workspace, in subclasses)."""
        return bool(np.all(pose >= self.low - 1e-9) and np.all(pose <= self.high + 1e-9))

    def speeds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per-axis velocity and acceleration of a move (subclasses)."""
        raise NotImplementedError

    def reference_speeds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per-axis velocity and acceleration of the reference move."""
        return self.speeds()

    def movable_mask(self, idx: list[int]) -> NDArray[np.bool_]:
        """Axes that act together with ``idx``: a move needs their servo and reference, and SVO and FRF switch
        and reference them at once (all six on a hexapod, as on PI's C-887)."""
        mask = np.zeros(len(self.axes), dtype=bool)
        mask[idx] = True
        return mask

    def _start_move(self, targets: list[tuple[int, float]], relative: bool) -> None:
        if self.referencing:
            raise GcsError(E.NOT_ALLOWED_IN_MOTION_MODE)
        idx = [i for i, _ in targets]
        need = self.movable_mask(idx)
        if not (self.servo[need].all() and self.referenced[need].all()):
            raise GcsError(E.MOVE_WITHOUT_REF_OR_NO_SERVO)
        pose = self.motion.target.copy()
        if relative:
            pose = np.where(self.motion.moving(), pose, self.motion.position())
        for i, v in targets:
            pose[i] = pose[i] + v if relative else v
        if not self.within_limits(pose):
            raise GcsError(E.POS_OUT_OF_LIMITS)
        self.motion.start_move(pose, *self.speeds())

    def _stop(self, session: Session) -> None:
        self.motion.halt()
        self.referencing = False
        session.fail(E.STOPPED)

    # ----- the commands -----
    def _idn_q(self, s: Session, a: list[str]) -> Reply:
        return [self.idn]

    def _csv_q(self, s: Session, a: list[str]) -> Reply:
        return ["2.0"]

    def _err_q(self, s: Session, a: list[str]) -> Reply:
        code, s.error = s.error, 0
        return [str(code)]

    def _hlp_q(self, s: Session, a: list[str]) -> Reply:
        return ["The following commands are valid:", *self.command_names, "end of help"]

    def _sai_q(self, s: Session, a: list[str]) -> Reply:
        return list(self.axes)

    def _svo(self, s: Session, a: list[str]) -> Reply:
        pairs = self._pairs(a)
        if any(v not in (0.0, 1.0) for _, v in pairs):
            raise GcsError(E.PARAM_OUT_OF_RANGE)
        if self.motion.moving().any() or self.referencing:
            raise GcsError(E.NOT_ALLOWED_WHILE_MOVING)
        for i, v in pairs:
            self.servo[self.movable_mask([i])] = bool(v)  # coupled axes (a hexapod) switch together
        return None

    def _svo_q(self, s: Session, a: list[str]) -> Reply:
        return self._axis_reply(self._axis_list(a), self.servo)

    def _frf(self, s: Session, a: list[str]) -> Reply:
        idx = self._axis_list(a)
        need = self.movable_mask(idx)
        if self.motion.moving().any():
            raise GcsError(E.NOT_ALLOWED_WHILE_MOVING)
        if not self.servo[need].all():
            raise GcsError(E.MOVE_WITHOUT_REF_OR_NO_SERVO)
        self.referenced[need] = False
        target = self.motion.position()
        target[need] = np.asarray(self.reference_pose, dtype=float)[need]
        self.referencing = True
        self.motion.start_move(target, *self.reference_speeds())
        return None

    def _frf_q(self, s: Session, a: list[str]) -> Reply:
        return self._axis_reply(self._axis_list(a), self.referenced)

    def _mov(self, s: Session, a: list[str]) -> Reply:
        self._start_move(self._pairs(a), relative=False)
        return None

    def _mvr(self, s: Session, a: list[str]) -> Reply:
        self._start_move(self._pairs(a), relative=True)
        return None

    def _mov_q(self, s: Session, a: list[str]) -> Reply:
        return self._axis_reply(self._axis_list(a), self.motion.target)

    def _pos_q(self, s: Session, a: list[str]) -> Reply:
        return self._axis_reply(self._axis_list(a), self.readback())

    def _ont_q(self, s: Session, a: list[str]) -> Reply:
        return self._axis_reply(self._axis_list(a), self.motion.on_target() & ~self.motion.moving())

    def _hlt(self, s: Session, a: list[str]) -> Reply:
        self._axis_list(a)  # validates the axes; a hexapod halts as a whole
        self._stop(s)
        return None

    def _stp(self, s: Session, a: list[str]) -> Reply:
        self._stop(s)
        return None

    def _tmn_q(self, s: Session, a: list[str]) -> Reply:
        return self._axis_reply(self._axis_list(a), self.low)

    def _tmx_q(self, s: Session, a: list[str]) -> Reply:
        return self._axis_reply(self._axis_list(a), self.high)

    def _char5(self, s: Session, a: list[str]) -> Reply:
        bits = sum(1 << i for i, m in enumerate(self.motion.moving()) if m)
        return [format(bits, "X")]

    def _char7(self, s: Session, a: list[str]) -> Reply:
        return [BUSY if self.referencing else READY]

    def _char24(self, s: Session, a: list[str]) -> Reply:
        self._stop(s)
        return None

    def readback(self) -> NDArray[np.float64]:
        """What ``POS?`` reports: the encoder position (subclasses add encoder noise)."""
        return self.motion.position()

    @staticmethod
    def _fmt(v: float) -> str:
        return format_value(float(v))
