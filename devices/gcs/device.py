"""Shared driver for PI GCS 2.0 motion controllers: connect by URI, query state, check limits, move, stop.

:class:`GcsMotionDevice` is written once; the transport is chosen at connect time
from the URI (``tcp://host:port`` or ``serial:///dev/ttyUSB0?baud=115200``; a ``sim://``
URI is resolved to a twin's loopback endpoint by :mod:`devices.sim` before a driver
sees it). Subclasses name the axes and add kind-specific commands (hexapod workspace
and pivot, stage velocity).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Mapping
from typing import Any, ClassVar, Self

from devices.base import AxisInfo, DeviceInfo, Driver, Status
from devices.errors import (
    ControllerError,
    DeviceError,
    DeviceTimeoutError,
    NotConnectedError,
    NotReferencedError,
    OutOfLimitsError,
    ProtocolError,
)
from devices.gcs import errors as E
from devices.gcs.client import GcsClient
from devices.gcs.framing import BUSY, READY, format_command, parse_axis_values
from devices.uri import Endpoint, parse_uri

DEFAULT_PORT = 50000


class ServoOffError(NotReferencedError):
    """A move was refused because the servo of an axis is off (switch it on with ``servo(True)``)."""

    def __init__(self, message: str, axes: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.axes = tuple(axes)  # the axes whose servo is off (user names)


class GcsMotionDevice(Driver):
    """Base driver: axes exposed under user names, mapped to the controller's axis identifiers."""

    kind: ClassVar[str] = "gcs"
    axis_map: ClassVar[dict[str, str]] = {}  # user name -> controller axis identifier
    units: ClassVar[dict[str, str]] = {}  # user name -> 'mm' | 'deg'
    reference_timeout_s: ClassVar[float] = 120.0

    def __init__(
        self,
        name: str,
        uri: str,
        *,
        timeout_s: float = 2.0,
        poll_s: float = 0.005,
        move_timeout_s: float | None = None,
        query_retries: int = 1,
        **unknown: Any,
    ) -> None:
        super().__init__(name, uri)
        if unknown:
            raise DeviceError(
                f"{name}: unknown option(s) {', '.join(sorted(unknown))}; driver options are timeout_s, "
                "poll_s, move_timeout_s, query_retries"
            )
        self.endpoint: Endpoint = parse_uri(uri, default_port=DEFAULT_PORT)
        if self.endpoint.scheme not in ("tcp", "serial"):
            raise DeviceError(f"{name}: GCS devices connect by tcp://host:port or serial://path, not {uri!r}")
        self.timeout_s = timeout_s
        self.poll_s = poll_s
        self.move_timeout_s = move_timeout_s
        self.query_retries = query_retries
        self._client: GcsClient | None = None
        self._idn = ""
        self._limits: dict[str, tuple[float, float]] = {}
        self._stopped = 0  # increments on stop(): running moves end with an error
        self._moves_sent = 0  # increments with every MOV/MVR: an earlier move still waiting is superseded
        self._last_move_of: dict[str, int] = {}  # axis -> the mark of the latest move that set its target

    # ----- connection -----
    @property
    def client(self) -> GcsClient:
        """The GCS client (raises :class:`NotConnectedError` before ``connect()``)."""
        if self._client is None:
            raise NotConnectedError(f"{self.name}: not connected (await connect() first)")
        return self._client

    async def connect(self) -> None:
        """Open the transport, identify the controller and read its axes and soft limits."""
        client = GcsClient(self.endpoint, timeout_s=self.timeout_s, query_retries=self.query_retries)
        await client.connect()
        self._client = client
        try:
            self._idn = (await client.query("*IDN?"))[0]
            axes = [ln.strip() for ln in await client.query("SAI?")]
            missing = [c for c in self.axis_map.values() if c not in axes]
            if missing:
                raise DeviceError(f"{self.name}: controller {self._idn!r} has axes {axes}, lacks {missing}")
            await self.limits(refresh=True)
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        """Close the transport and release what was attached to this driver (idempotent)."""
        client, self._client = self._client, None
        if client is not None:
            await client.close()
        await self._release()

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ----- queries -----
    async def _axis_query(self, command: str) -> dict[str, float]:
        def parse(lines: list[str]) -> dict[str, float]:
            values = parse_axis_values(lines, command)
            try:
                return {user: values[ctrl] for user, ctrl in self.axis_map.items()}
            except KeyError as exc:
                raise ProtocolError(f"{self.name}: reply to {command!r} lacks axis {exc}") from None

        ctrl_axes = " ".join(self.axis_map.values())
        return await self.client.query(f"{command} {ctrl_axes}", parse)

    async def position(self) -> dict[str, float]:
        """Read-back positions (``POS?``) in mm / deg."""
        return await self._axis_query("POS?")

    async def target(self) -> dict[str, float]:
        """Commanded targets (``MOV?``) in mm / deg."""
        return await self._axis_query("MOV?")

    async def on_target(self) -> bool:
        """Whether every axis is on target (``ONT?``)."""
        return all(v != 0 for v in (await self._axis_query("ONT?")).values())

    async def referenced(self) -> dict[str, bool]:
        """Per axis: referenced (``FRF?``)."""
        return {k: v != 0 for k, v in (await self._axis_query("FRF?")).items()}

    async def servo_on(self) -> dict[str, bool]:
        """Per axis: servo on (``SVO?``)."""
        return {k: v != 0 for k, v in (await self._axis_query("SVO?")).items()}

    async def moving(self) -> bool:
        """Whether any axis moves (``#5``)."""

        def parse(lines: list[str]) -> int:
            try:
                return int(lines[0].strip(), 16)
            except (ValueError, IndexError):
                raise ProtocolError(f"{self.name}: unreadable #5 reply {lines!r}") from None

        return bool(await self.client.query("#5", parse))

    async def ready(self) -> bool:
        """Whether the controller is ready (``#7``; busy while referencing)."""

        def parse(lines: list[str]) -> bool:
            if lines and lines[0] in (READY, BUSY):
                return lines[0] == READY
            raise ProtocolError(f"{self.name}: unreadable #7 reply {lines!r}")

        return await self.client.query("#7", parse)

    async def limits(self, refresh: bool = False) -> dict[str, tuple[float, float]]:
        """Soft limits per axis (``TMN?``/``TMX?``) in mm / deg."""
        if refresh or not self._limits:
            low, high = await self._axis_query("TMN?"), await self._axis_query("TMX?")
            self._limits = {k: (low[k], high[k]) for k in self.axis_map}
        return dict(self._limits)

    async def describe(self) -> DeviceInfo:
        """Model, serial, firmware, axes with units and soft limits."""
        parts = [p.strip() for p in self._idn.split(",")] + ["", "", "", ""]
        limits = await self.limits()
        axes = tuple(AxisInfo(k, self.units[k], *limits[k]) for k in self.axis_map)
        extra = {"idn": self._idn, "axis_map": dict(self.axis_map), "kind": self.kind}
        return DeviceInfo(self.name, parts[1], parts[2], parts[3], axes, self.uri, extra)

    async def read(self) -> dict[str, Any]:
        """Positions, targets, on-target, referenced and servo state, moving."""
        return {
            "position": await self.position(),
            "target": await self.target(),
            "on_target": await self.on_target(),
            "referenced": await self.referenced(),
            "servo": await self.servo_on(),
            "moving": await self.moving(),
        }

    # ----- checks -----
    def check_velocity(self, value: float, unit: str) -> float:
        """A velocity to send: a positive finite number, else :class:`OutOfLimitsError` (nothing sent)."""
        v = float(value)
        if not (math.isfinite(v) and v > 0.0):
            raise OutOfLimitsError(
                f"{self.name}: velocity {value} {unit} must be a positive finite number; nothing changed"
            )
        return v

    def check_limits(self, targets: Mapping[str, float]) -> dict[str, float]:
        """Validate axis names and values against the soft limits; raise :class:`OutOfLimitsError` naming the axis."""
        if not targets:
            raise DeviceError(f"{self.name}: no targets given (axes: {', '.join(self.axis_map)})")
        out: dict[str, float] = {}
        for axis, value in targets.items():
            if axis not in self.axis_map:
                raise DeviceError(f"{self.name}: unknown axis {axis!r}; axes are {', '.join(self.axis_map)}")
            v = float(value)
            if not math.isfinite(v):
                raise OutOfLimitsError(f"{self.name}: target {axis}={value} is not a finite number")
            lo, hi = self._limits[axis]
            if not lo <= v <= hi:
                raise OutOfLimitsError(
                    f"{self.name}: target {axis}={v:g} {self.units[axis]} is outside the soft limits "
                    f"[{lo:g}, {hi:g}] {self.units[axis]}; nothing moved"
                )
            out[axis] = v
        return out

    async def check_pose(
        self, targets: Mapping[str, float], current: Mapping[str, float] | None = None
    ) -> dict[str, float]:
        """Check a target against the limits (and, on coupled machines, the workspace) before moving.

        ``current``: the present targets (``MOV?``), if the caller already has them.
        """
        return self.check_limits(targets)

    async def _explain_refusal(self, exc: ControllerError) -> DeviceError:
        """Turn GCS error 5 into a precise reason (servo off / not referenced)."""
        if exc.code != E.MOVE_WITHOUT_REF_OR_NO_SERVO:
            return exc
        servo, ref = await self.servo_on(), await self.referenced()
        off = [k for k, v in servo.items() if not v]
        if off:
            return ServoOffError(
                f"{self.name}: servo off on {', '.join(off)}; switch it on with servo(True); nothing moved", tuple(off)
            )
        unref = [k for k, v in ref.items() if not v]
        if not unref:
            return exc  # the controller's own reason (servo and reference look fine from here)
        return NotReferencedError(
            f"{self.name}: axes {', '.join(unref)} not referenced; run reference() first; nothing moved"
        )

    # ----- actions -----
    async def servo(self, on: bool = True) -> None:
        """Switch the servo of every axis on or off (``SVO``)."""
        await self.client.command(format_command("SVO", {c: bool(on) for c in self.axis_map.values()}))

    def _status(self, action: str, factory: Any) -> Status[None]:
        box: list[Status[None]] = []
        status: Status[None] = Status(f"{self.name}.{action}", factory(box))
        box.append(status)  # the coroutine starts later and finds its status here
        return status

    def move(self, targets: Mapping[str, float]) -> Status[None]:
        """Absolute move (mm / deg), checked before anything moves; the status ends on target."""
        return self._status("move", lambda box: self._move(dict(targets), False, box))

    def move_relative(self, steps: Mapping[str, float]) -> Status[None]:
        """Relative move (``MVR``), checked against the limits from the current targets first."""
        return self._status("move_relative", lambda box: self._move(dict(steps), True, box))

    async def _move(self, targets: dict[str, float], relative: bool, box: list[Status[None]]) -> None:
        status = box[0] if box else None
        start = await self.target()
        if relative:
            for k in targets:
                if k not in self.axis_map:
                    raise DeviceError(f"{self.name}: unknown axis {k!r}; axes are {', '.join(self.axis_map)}")
            absolute = {k: start[k] + float(v) for k, v in targets.items()}
        else:
            absolute = targets
        checked = await self.check_pose(absolute, current=start)
        stop_mark = self._stopped
        command = "MVR" if relative else "MOV"
        sent = {self.axis_map[k]: float(targets[k]) for k in checked}
        self._moves_sent += 1
        move_mark = self._moves_sent
        self._last_move_of.update(dict.fromkeys(checked, move_mark))
        self._check_interlock("move")
        try:
            await self.client.command(format_command(command, sent))
        except ControllerError as exc:
            raise await self._explain_refusal(exc) from None
        try:
            await self._wait_on_target(checked, start, (stop_mark, move_mark), status)
        except asyncio.CancelledError:
            await asyncio.shield(self.halt())
            raise

    def _estimate_s(self, start: Mapping[str, float], targets: Mapping[str, float]) -> float:
        """Upper bound for a move's travel time (subclasses know the velocity)."""
        return 60.0

    async def _wait_on_target(
        self, targets: dict[str, float], start: dict[str, float], marks: tuple[int, int], status: Status[None] | None
    ) -> None:
        limit = self.move_timeout_s or (2.0 * self._estimate_s(start, targets) + 2.0)
        t0 = time.monotonic()
        polls = 0
        while True:
            if self._stopped != marks[0]:
                raise ControllerError(E.STOPPED, E.error_text(E.STOPPED), "MOV")
            retargeted = [k for k in targets if self._last_move_of.get(k) != marks[1]]
            if (
                retargeted
            ):  # a later move owns these axes now: this one ends here and never halts them at its time limit
                raise ControllerError(
                    E.STOPPED, f"move superseded by a later move on {', '.join(retargeted)} before it arrived", "MOV"
                )
            ont = await self._axis_query("ONT?")
            if all(v != 0 for v in ont.values()):
                await self._check_arrived(targets, marks)
                if status is not None:
                    status.report(current=dict(targets), target=targets, fraction=1.0, message="on target")
                return
            polls += 1
            if status is not None and polls % 10 == 0:
                pos = await self.position()
                status.report(current=pos, target=targets, fraction=_fraction(start, pos, targets))
            if time.monotonic() - t0 > limit:
                stuck = [k for k, v in ont.items() if not v]
                await self.halt()
                raise DeviceTimeoutError(
                    f"{self.name}: axes {', '.join(stuck)} not on target after {limit:.1f} s (stuck?); motion halted"
                )
            await asyncio.sleep(self.poll_s)

    async def _check_arrived(self, targets: Mapping[str, float], marks: tuple[int, int]) -> None:
        """On target, but at *our* target? (a halt, a later move or another client ends a move early)."""
        if self._stopped != marks[0]:
            raise ControllerError(E.STOPPED, E.error_text(E.STOPPED), "MOV")
        now = await self.target()
        off = [k for k, v in targets.items() if abs(now[k] - v) > 1e-5]
        if off:
            why = "superseded by a later move" if self._moves_sent != marks[1] else "halted (by another client?)"
            raise ControllerError(E.STOPPED, f"move ended away from its target on {', '.join(off)}: {why}", "MOV")

    def reference(self) -> Status[None]:
        """Servo on, then reference every axis (``FRF``); the status ends when all are referenced."""
        return self._status("reference", self._reference)

    async def _reference(self, box: list[Status[None]]) -> None:
        try:
            await self._referencing(box[0] if box else None)
        except asyncio.CancelledError:
            await asyncio.shield(self.halt())
            raise

    async def _referencing(self, status: Status[None] | None) -> None:
        if not all((await self.servo_on()).values()):
            await self.servo(True)
        self._check_interlock("referencing")
        await self.client.command(format_command("FRF", list(self.axis_map.values())))
        t0 = time.monotonic()
        while not await self.ready():
            if time.monotonic() - t0 > self.reference_timeout_s:
                await self.halt()
                raise DeviceTimeoutError(
                    f"{self.name}: referencing not done within {self.reference_timeout_s:g} s; halted"
                )
            if status is not None:
                status.report(message="referencing")
            await asyncio.sleep(max(self.poll_s, 0.02))
        ref = await self.referenced()
        if not all(ref.values()):
            raise NotReferencedError(
                f"{self.name}: referencing failed for {', '.join(k for k, v in ref.items() if not v)}"
            )
        if status is not None:
            status.report(message="referenced", fraction=1.0)

    async def halt(self) -> None:
        """Halt every axis now (``#24``, sent without waiting for other traffic) and clear the resulting error 10.

        Stopping is safe to repeat: if the connection turns out to be dead, ``#24`` is sent
        again over the fresh one.
        """
        self._stopped += 1
        client = self.client
        for _ in range(2):
            reconnects = client.stats["reconnects"]
            await client.send_now("#24")
            code = await client.error()
            if client.stats["reconnects"] == reconnects:
                break
        if code not in (0, E.STOPPED):
            raise E.controller_error(code, "#24")

    async def stop(self) -> None:
        """Halt every axis now (one round trip); running move statuses end with error 10."""
        await self.halt()


def _fraction(start: Mapping[str, float], now: Mapping[str, float], target: Mapping[str, float]) -> float:
    total = sum(abs(target[k] - start[k]) for k in target)
    if total <= 0:
        return 1.0
    left = sum(abs(target[k] - now[k]) for k in target)
    return max(0.0, min(1.0, 1.0 - left / total))
