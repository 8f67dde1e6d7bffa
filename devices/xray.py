"""X-ray generator driver over Modbus TCP (pymodbus 3.x), register map in :mod:`devices.xray_registers`.

Safety rules: nothing is requested while the door interlock is open or a fault is active;
an exposure request is sent once and never retried (a lost reply is an error, and X-rays are
switched off); reads, settings and :meth:`XrayGenerator.xray_off` reconnect once when the link
dropped. A heartbeat task keeps the generator's watchdog fed and notices a silent generator.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException

from devices import xray_registers as reg
from devices.base import DeviceInfo, Driver, Status
from devices.errors import (
    ControllerError,
    DeviceError,
    DeviceTimeoutError,
    FaultActiveError,
    InterlockOpenError,
    NotConnectedError,
    OutOfLimitsError,
    ProtocolError,
    UriError,
)
from devices.uri import option_number, parse_uri
from devices.xray_registers import FaultCode, GeneratorState, Refusal

DEFAULT_PORT = 502
log = logging.getLogger(__name__)
# pymodbus logs a late reply it skips (one to a request this driver cut short) or a send on a closed link as an ERROR
# with a dump of the last frames, which reached the operator's terminal in the middle of a scan: this driver names
# every failure itself, so only pymodbus's critical messages get through
logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
_OPTIONS = {"timeout_s", "heartbeat_s", "watchdog_ms", "prep_timeout_s", "poll_s", "device_id", "hold_s", "monitor"}


def _options(uri_params: dict[str, str], options: dict[str, Any]) -> dict[str, float]:
    merged: dict[str, Any] = {**uri_params, **options}
    unknown = sorted(set(merged) - _OPTIONS)
    if unknown:
        raise UriError(
            f"X-ray generator: unknown option(s) {', '.join(unknown)}; allowed: {', '.join(sorted(_OPTIONS))}"
        )
    try:
        return {k: option_number(v) for k, v in merged.items()}
    except UriError as exc:
        raise UriError(f"X-ray generator: options must be finite numbers ({exc})") from None


def _retrieve(task: asyncio.Future[Any]) -> None:
    if not task.cancelled():
        task.exception()


class XrayGenerator(Driver):
    """Driver of a Modbus TCP X-ray generator (``modbus://host:port`` or ``tcp://host:port``)."""

    def __init__(self, name: str = "xray", uri: str = "modbus://127.0.0.1:502", **options: Any) -> None:
        super().__init__(name, uri)
        self.endpoint = parse_uri(uri, default_port=DEFAULT_PORT)
        if self.endpoint.scheme not in ("tcp", "modbus"):
            raise UriError(f"X-ray generator {name!r}: URI must be modbus://host:port or tcp://host:port, got {uri!r}")
        opts = _options(self.endpoint.params, options)
        self.timeout_s = opts.get("timeout_s", 1.0)
        self.heartbeat_s = opts.get("heartbeat_s", 0.25)
        self.watchdog_ms = int(opts.get("watchdog_ms", reg.WATCHDOG_MS_DEFAULT if self.heartbeat_s > 0 else 0))
        self.prep_timeout_s = opts.get("prep_timeout_s", 5.0)
        self.poll_s = opts.get("poll_s", 0.005)
        self.device_id = int(opts.get("device_id", reg.DEVICE_ID))
        # high voltage stays on after an exposure (or a prepare) only this long without the next one; None: until xray_off()
        self.hold_s: float | None = opts.get("hold_s")
        # the last exposure's start and end (time.monotonic()): the start half the request's exchange after it
        # left, the end at most its set time after that
        self.last_exposure_s: tuple[float, float] | None = None
        # a second connection that only reads and switches X-rays off (a safety monitor beside the scan's own):
        # it sets no watchdog, sends no heartbeat and leaves the generator as it is when it closes
        self.monitor = bool(opts.get("monitor", 0.0))
        if self.monitor:
            self.heartbeat_s, self.watchdog_ms = 0.0, 0
        self._client: AsyncModbusTcpClient | None = None
        self._host, self._port = self.endpoint.host, self.endpoint.port
        self._opened = False
        self._garbled = asyncio.Event()  # set when a reply that cannot be ours arrives (one per connection)
        self._asked: dict[int, tuple[int, int]] = {}  # transaction id -> function code and count of the request
        self._heartbeat_task: asyncio.Task[None] | None = None
        self._heartbeat_error: DeviceTimeoutError | None = None  # set while the generator's heartbeat is frozen
        self._hb_counter = 0
        self._action_lock = asyncio.Lock()
        self._hold_task: asyncio.Task[None] | None = None
        self._hold_sending = False
        self._link_fault: tuple[float, str, str] | None = None  # link trouble: last seen, when it began, its cause
        self._link_down = False  # no heartbeat has gone through since the last link fault

    # ------------------------------------------------------------- connection
    async def connect(self) -> None:
        """Open the link, set the watchdog, start the heartbeat."""
        await self._open_client()
        self._opened = True
        if self.monitor:
            return
        await self._request(
            "set watchdog", lambda c: c.write_register(reg.WATCHDOG_MS, self.watchdog_ms, device_id=self.device_id)
        )
        if self.heartbeat_s > 0 and self._heartbeat_task is None:
            self._heartbeat_task = asyncio.ensure_future(self._heartbeat())

    async def _open_client(self) -> None:
        if self._client is not None:
            self._client.close()
        self._garbled, self._asked = asyncio.Event(), {}
        self._client = AsyncModbusTcpClient(
            self._host,
            port=int(self._port or DEFAULT_PORT),
            timeout=self.timeout_s,
            retries=0,
            reconnect_delay=0,
            trace_packet=self._check_packet,
            trace_pdu=self._check_reply,
        )
        try:
            async with asyncio.timeout(self.timeout_s + 1.0):  # unlike wait_for, never swallows a cancellation
                ok = await self._client.connect()
        except TimeoutError:
            ok = False
        if not ok:
            raise NotConnectedError(f"{self.name}: cannot connect to X-ray generator at {self._host}:{self._port}")

    async def close(self) -> None:
        """Switch X-rays off (best effort), stop the heartbeat, close the link, release what was attached."""
        await self._cancel_hold()
        if self._heartbeat_task is not None:
            self._heartbeat_task.cancel()
            with contextlib.suppress(BaseException):
                await self._heartbeat_task
            self._heartbeat_task = None
        if self._opened and not self.monitor:
            with contextlib.suppress(DeviceError):
                await self.xray_off()
        self._opened = False
        if self._client is not None:
            self._client.close()
            self._client = None
        await self._release()

    async def __aenter__(self) -> XrayGenerator:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # --------------------------------------------------------------- transport
    def _check_packet(self, sending: bool, data: bytes) -> bytes:
        """Flag replies whose MBAP header cannot be ours (pymodbus silently skips them)."""
        if not sending and len(data) >= 8:
            length = int.from_bytes(data[4:6], "big")
            fc = data[7]
            bad_header = data[2:4] != b"\x00\x00" or data[6] != self.device_id or not 2 <= length <= 254
            bad_fc = (fc & 0x7F) not in (1, 2, 3, 4, 5, 6, 15, 16)
            bad_count = fc in (1, 2, 3, 4) and len(data) >= 9 and data[8] != length - 3
            if bad_header or bad_fc or bad_count:
                self._garbled.set()  # every request in flight fails now, not at its time-out
        return data

    def _check_reply(self, sending: bool, pdu: Any) -> Any:
        """Flag a reply that answers another request than the one that bears its transaction id: another function,
        or fewer values than asked for (pymodbus matches the id only; a device or gateway that answers a request cut
        short with a later one's id would otherwise hand one read's values to another)."""
        if sending:
            if len(self._asked) > 64:  # requests cut short are never answered: forget the oldest
                self._asked.pop(next(iter(self._asked)))
            self._asked[pdu.transaction_id] = (pdu.function_code, int(getattr(pdu, "count", 0) or 0))
            return pdu
        asked = self._asked.pop(pdu.transaction_id, None)
        if asked is not None:
            fc, count = asked
            got = pdu.function_code & 0x7F
            short = not pdu.function_code & 0x80 and (
                (fc in (1, 2) and len(pdu.bits) < count) or (fc in (3, 4) and len(pdu.registers) < count)
            )
            if got != fc or short:
                self._garbled.set()  # the stream is out of step: the request in flight fails and the link starts afresh
        return pdu

    async def _request(
        self, what: str, call: Callable[[AsyncModbusTcpClient], Awaitable[Any]], *, retry: bool = True
    ) -> Any:
        """Run one Modbus request; map failures to named errors; reconnect and repeat once if ``retry``."""
        for attempt in range(2 if retry else 1):
            last = attempt == (1 if retry else 0)
            try:
                return await self._request_once(what, call)
            except (NotConnectedError, DeviceTimeoutError, ProtocolError):
                if last or not self._opened:
                    raise
                await self._open_client()
        raise AssertionError("unreachable")

    async def _request_once(self, what: str, call: Callable[[AsyncModbusTcpClient], Awaitable[Any]]) -> Any:
        client = self._client
        if client is None or not client.connected:
            raise NotConnectedError(f"{self.name}: not connected to the X-ray generator ({what})")
        garbled = self._garbled
        try:
            async with asyncio.timeout(self.timeout_s * 2 + 0.5):
                reply = await self._unless_garbled(call(client), garbled)
        except ConnectionException:
            raise NotConnectedError(f"{self.name}: connection to the X-ray generator lost ({what})") from None
        except (TimeoutError, ModbusException):
            if garbled.is_set():
                client.close()  # the byte stream is out of step: start afresh on the next request
                raise ProtocolError(
                    f"{self.name}: garbled reply from the X-ray generator, or one to another request ({what})"
                ) from None
            if not client.connected:
                raise NotConnectedError(f"{self.name}: X-ray generator dropped the connection ({what})") from None
            raise DeviceTimeoutError(
                f"{self.name}: no reply from the X-ray generator within {self.timeout_s:g} s ({what})"
            ) from None
        task = asyncio.current_task()
        if task is not None and task.cancelling():
            raise asyncio.CancelledError  # pymodbus's inner wait_for can swallow a cancellation: honour it here
        if reply.isError():
            code = int(getattr(reply, "exception_code", 0))
            text = reg.MODBUS_EXCEPTIONS.get(code, "unknown exception")
            raise ControllerError(code, f"Modbus exception {text}", what)
        return reply

    @staticmethod
    async def _unless_garbled(request: Awaitable[Any], garbled: asyncio.Event) -> Any:
        """The request's reply, or ModbusException as soon as a garbled packet arrives on the link."""
        call = asyncio.ensure_future(request)
        watch = asyncio.ensure_future(garbled.wait())
        try:
            await asyncio.wait({call, watch}, return_when=asyncio.FIRST_COMPLETED)
            if garbled.is_set():  # first: a reply to another request arrives as a done call
                raise ModbusException("garbled packet on the link")
            return call.result()
        finally:
            for task in (call, watch):
                if not task.done():
                    # not awaited: a Modbus request cut short may never end on its own (its late reply is
                    # skipped by transaction id); waiting for it here would hang the caller
                    task.cancel()
                    task.add_done_callback(_retrieve)

    async def _read_inputs(self) -> list[bool]:
        r = await self._request(
            "read inputs", lambda c: c.read_discrete_inputs(0, count=reg.N_INPUTS, device_id=self.device_id)
        )
        return list(r.bits[: reg.N_INPUTS])

    async def _read_input_registers(self) -> list[int]:
        r = await self._request(
            "read status", lambda c: c.read_input_registers(0, count=reg.N_INPUT_REGS, device_id=self.device_id)
        )
        return list(r.registers)

    async def _write_coil(self, coil: int, value: bool, *, retry: bool = True) -> None:
        await self._request(
            f"write coil {coil}={int(value)}",
            lambda c: c.write_coil(coil, value, device_id=self.device_id),
            retry=retry,
        )

    # -------------------------------------------------------------- heartbeat
    async def _heartbeat(self) -> None:
        last_value, last_change = -1, time.monotonic()
        limit_s = max(self.watchdog_ms / 1000.0, 4 * self.heartbeat_s, 0.5)
        while True:
            await asyncio.sleep(self.heartbeat_s)
            self._hb_counter = (self._hb_counter + 1) & 0xFFFF
            try:
                await self._request(
                    "heartbeat",
                    lambda c: c.write_register(reg.HEARTBEAT_IN, self._hb_counter, device_id=self.device_id),
                    retry=False,
                )
                r = await self._request(
                    "heartbeat",
                    lambda c: c.read_input_registers(reg.HEARTBEAT_OUT, count=1, device_id=self.device_id),
                    retry=False,
                )
            except ProtocolError as exc:
                # a garbled reply leaves the stream out of step, not the link down: start afresh at once, so the
                # generator's watchdog does not fire for want of a heartbeat (and remember why, should it fire)
                self._note_link_fault(exc)
                with contextlib.suppress(DeviceError):
                    await self._open_client()
                continue
            except DeviceError as exc:
                # no reconnect from here: a lost link lets the generator's own watchdog switch X-rays off
                self._note_link_fault(exc)
                continue  # link trouble is reported by the next action; the generator's watchdog keeps it safe
            self._link_down = False
            value = int(r.registers[0])
            if value != last_value:
                last_value, last_change = value, time.monotonic()
                self._heartbeat_error = None
            elif time.monotonic() - last_change > limit_s:
                self._heartbeat_error = DeviceTimeoutError(
                    f"{self.name}: generator heartbeat stopped for {time.monotonic() - last_change:.1f} s"
                )

    def _note_link_fault(self, exc: DeviceError) -> None:
        """Remember link trouble: the fault that began it (a timeout is followed by "not connected" until the link
        is back; the cause is what a watchdog fault names) and when it was last seen."""
        if self._link_fault is None or not self._link_down:
            self._link_fault = (time.monotonic(), time.strftime("%H:%M:%S"), str(exc).removeprefix(f"{self.name}: "))
        else:
            self._link_fault = (time.monotonic(), *self._link_fault[1:])
        self._link_down = True

    def _fault_text(self, code: int) -> str:
        """``fault N (NAME)``, with the link fault that starved the watchdog when one came shortly before it."""
        name = FaultCode(code).name if code in FaultCode._value2member_map_ else str(code)
        text = f"generator fault {code} ({name})"
        if code == FaultCode.WATCHDOG and self._link_fault is not None:
            t, clock, what = self._link_fault
            if time.monotonic() - t < max(self.watchdog_ms / 1000.0, 1.0) + 10.0:
                text += f": the watchdog expired after a link fault at {clock} ({what})"
        return text

    def _check_heartbeat(self) -> None:
        if self._heartbeat_error is not None:
            raise self._heartbeat_error

    # ------------------------------------------------------------------ API
    async def describe(self) -> DeviceInfo:
        """Model, serial, firmware and the setting ranges."""
        ir = await self._read_input_registers()
        fw = ir[reg.FIRMWARE]
        return DeviceInfo(
            name=self.name,
            model=reg.registers_to_text(ir[reg.MODEL : reg.MODEL + reg.TEXT_REGISTERS]),
            serial=reg.registers_to_text(ir[reg.SERIAL : reg.SERIAL + reg.TEXT_REGISTERS]),
            firmware=f"{fw // 100}.{fw % 100:02d}",
            uri=self.uri,
            extra={"kv_range": reg.KV_RANGE, "ma_range": reg.MA_RANGE, "exposure_ms_range": reg.EXPOSURE_MS_RANGE},
        )

    async def read(self) -> dict[str, Any]:
        """State, settings, acknowledgements, interlock, fault code and frame counter as plain values."""
        ir = await self._read_input_registers()
        di = await self._read_inputs()
        hr = (
            await self._request(
                "read settings", lambda c: c.read_holding_registers(0, count=reg.N_HOLDING, device_id=self.device_id)
            )
        ).registers
        return {
            "state": GeneratorState(ir[reg.STATE]).name,
            "fault_code": int(ir[reg.FAULT_CODE]),
            "fault": FaultCode(ir[reg.FAULT_CODE]).name
            if ir[reg.FAULT_CODE] in FaultCode._value2member_map_
            else "UNKNOWN",
            "refusal": Refusal(ir[reg.REFUSAL]).name if ir[reg.REFUSAL] in Refusal._value2member_map_ else "UNKNOWN",
            "door_closed": bool(di[reg.DOOR_CLOSED]),
            "ready": bool(di[reg.READY_ACK]),
            "exposing": bool(di[reg.EXPOSING_ACK]),
            "hv_on": bool(di[reg.HV_ON]),
            "kv": hr[reg.KV_SET] / reg.KV_SCALE,
            "ma": hr[reg.MA_SET] / reg.MA_SCALE,
            "exposure_ms": int(hr[reg.EXPOSURE_MS]),
            "kv_actual": ir[reg.KV_ACTUAL] / reg.KV_SCALE,
            "ma_actual": ir[reg.MA_ACTUAL] / reg.MA_SCALE,
            "frame_counter": (ir[reg.FRAME_COUNTER_HI] << 16) | ir[reg.FRAME_COUNTER_LO],
            "last_exposure_ms": int(ir[reg.LAST_EXPOSURE_MS]),
            "heartbeat": int(ir[reg.HEARTBEAT_OUT]),
        }

    async def configure(self, kv: float, ma: float, exposure_ms: float) -> None:
        """Set tube voltage (kV), current (mA) and exposure time (ms); checked against the ranges first."""
        checks = (
            ("kv", kv, reg.KV_RANGE),
            ("ma", ma, reg.MA_RANGE),
            ("exposure_ms", exposure_ms, reg.EXPOSURE_MS_RANGE),
        )
        for what, value, (lo, hi) in checks:
            if not lo <= float(value) <= hi:
                raise OutOfLimitsError(
                    f"{self.name}: {what}={value:g} outside the allowed range {lo:g}..{hi:g}; nothing changed"
                )
        values = [int(round(kv * reg.KV_SCALE)), int(round(ma * reg.MA_SCALE)), int(round(exposure_ms))]
        await self._request("configure", lambda c: c.write_registers(reg.KV_SET, values, device_id=self.device_id))
        back = (
            await self._request(
                "configure", lambda c: c.read_holding_registers(reg.KV_SET, count=3, device_id=self.device_id)
            )
        ).registers
        if list(back[:3]) != values:
            raise ProtocolError(f"{self.name}: settings read back as {list(back[:3])}, wrote {values}")

    async def check_ready(self) -> None:
        """Raise unless the generator could expose now: no fault latched, door closed (switches nothing on)."""
        await self._check_can_expose()

    async def _check_can_expose(self) -> tuple[list[int], list[bool]]:
        self._check_heartbeat()
        ir = await self._read_input_registers()
        di = await self._read_inputs()
        if ir[reg.STATE] == GeneratorState.FAULT or di[reg.FAULT_ACTIVE]:
            raise FaultActiveError(
                f"{self.name}: {self._fault_text(ir[reg.FAULT_CODE])} is active; X-rays are off; "
                "reset the fault once its cause is gone"
            )
        if not di[reg.DOOR_CLOSED]:
            raise InterlockOpenError(
                f"{self.name}: door interlock is open; close the door before preparing or exposing"
            )
        return ir, di

    async def _raise_for_state(self, ir: list[int], what: str) -> None:
        state = ir[reg.STATE]
        if state == GeneratorState.FAULT:
            code = ir[reg.FAULT_CODE]
            if code == FaultCode.INTERLOCK_OPENED:
                raise InterlockOpenError(f"{self.name}: door opened during {what}; X-rays off, exposure lost")
            name = FaultCode(code).name if code in FaultCode._value2member_map_ else str(code)
            raise FaultActiveError(f"{self.name}: generator fault {code} ({name}) during {what}; X-rays off")
        refusal = ir[reg.REFUSAL]
        if refusal == Refusal.INTERLOCK_OPEN:
            raise InterlockOpenError(f"{self.name}: generator refused {what}: door interlock open; nothing exposed")
        if refusal == Refusal.FAULT_ACTIVE:
            raise FaultActiveError(f"{self.name}: generator refused {what}: fault active; nothing exposed")
        if refusal == Refusal.NOT_READY:
            raise DeviceError(f"{self.name}: generator refused {what}: not READY; nothing exposed")

    async def _wait_state(self, status: Status[Any], targets: set[int], what: str, timeout_s: float) -> list[int]:
        t0 = time.monotonic()
        while True:
            ir = await self._read_input_registers()
            state = ir[reg.STATE]
            elapsed = time.monotonic() - t0
            status.report(message=GeneratorState(state).name, fraction=min(1.0, elapsed / max(timeout_s, 1e-9)))
            if state in targets:
                return ir
            if state in (GeneratorState.FAULT, GeneratorState.IDLE):
                await self._raise_for_state(ir, what)
                raise DeviceError(f"{self.name}: generator returned to {GeneratorState(state).name} during {what}")
            if elapsed > timeout_s:
                raise DeviceTimeoutError(
                    f"{self.name}: {what} not finished within {timeout_s:g} s (state {GeneratorState(state).name})"
                )
            await asyncio.sleep(self.poll_s)

    def prepare(self) -> Status[None]:
        """Request PREP and wait for READY (refused while the door is open or a fault is active)."""
        status: Status[None]
        status = Status(f"{self.name}.prepare", self._guarded(lambda: self._prepare(status), self.hold_s))
        return status

    async def _prepare(self, status: Status[None]) -> None:
        ir, _ = await self._check_can_expose()
        if ir[reg.STATE] == GeneratorState.READY:
            return
        if ir[reg.STATE] not in (GeneratorState.IDLE, GeneratorState.PREP, GeneratorState.DONE):
            raise DeviceError(f"{self.name}: cannot prepare in state {GeneratorState(ir[reg.STATE]).name}")
        if ir[reg.STATE] == GeneratorState.DONE:
            await self._write_coil(reg.EXPOSE_REQ, False)  # a previous exposure was never released
        self._check_interlock("high voltage")
        await self._write_coil(reg.PREP_REQ, True)
        await self._wait_state(status, {GeneratorState.READY}, "prepare", self.prep_timeout_s)

    def expose(self, *, release: bool = False) -> Status[int]:
        """One exposure with the configured settings (prepares first if needed); ends with the new frame counter.

        ``release``: high voltage off as soon as the exposure is over (the next one is further away than a
        preparation takes); otherwise it stays on for at most :attr:`hold_s`.
        """
        status: Status[int]
        status = Status(
            f"{self.name}.expose", self._guarded(lambda: self._expose(status), 0.0 if release else self.hold_s)
        )
        return status

    def trigger(self) -> Status[int]:
        """Same as :meth:`expose` (the :class:`~devices.base.Triggerable` protocol)."""
        return self.expose()

    async def _expose(self, status: Status[int]) -> int:
        ir, _ = await self._check_can_expose()
        if ir[reg.STATE] != GeneratorState.READY:
            await self._prepare(status)  # type: ignore[arg-type]
            ir, _ = await self._check_can_expose()
        before = (ir[reg.FRAME_COUNTER_HI] << 16) | ir[reg.FRAME_COUNTER_LO]
        hr = await self._request(
            "read settings", lambda c: c.read_holding_registers(0, count=reg.N_HOLDING, device_id=self.device_id)
        )
        exposure_s = hr.registers[reg.EXPOSURE_MS] / 1000.0
        try:
            await self._write_coil(reg.EXPOSE_REQ, False)  # the request acts on a rising edge: start from low
            self._check_interlock("high voltage")
            # sent exactly once: a lost request or reply is an error, never a second exposure
            self.last_exposure_s = None
            t_sent = time.monotonic()
            await self._write_coil(reg.EXPOSE_REQ, True, retry=False)
            t_start = 0.5 * (t_sent + time.monotonic())
            ir = await self._wait_state(
                status, {GeneratorState.DONE}, "exposure", exposure_s * 2 + self.timeout_s + 1.0
            )
            self.last_exposure_s = (t_start, t_start + min(exposure_s, max(time.monotonic() - t_start, 0.0)))
        except DeviceError as exc:
            with contextlib.suppress(DeviceError):
                await self.xray_off()
            if isinstance(exc, (NotConnectedError, DeviceTimeoutError, ProtocolError)):
                raise type(exc)(f"{exc}; exposure outcome unknown, X-rays switched off, NOT retried") from None
            raise
        after = (ir[reg.FRAME_COUNTER_HI] << 16) | ir[reg.FRAME_COUNTER_LO]
        await self._write_coil(reg.EXPOSE_REQ, False)
        if after != before + 1:
            raise DeviceError(
                f"{self.name}: exposure reported DONE but the frame counter went {before} -> {after} (missing frame); not retried"
            )
        status.report(message="DONE", fraction=1.0, current={"frame_counter": float(after)})
        return after

    async def _guarded(self, fn: Callable[[], Awaitable[Any]], hold_s: float | None = None) -> Any:
        """One prepare/expose at a time; a cancelled one (an abort) switches X-rays off.

        Afterwards high voltage stays on for at most ``hold_s`` (None: until :meth:`xray_off`), unless the next
        prepare or exposure comes first: X-rays are off whenever nothing is exposing for longer than that.
        """
        if self._action_lock.locked():
            raise DeviceError(f"{self.name}: another prepare/expose is still running")
        async with self._action_lock:
            await self._cancel_hold()
            try:
                result = await fn()
            except asyncio.CancelledError:
                with contextlib.suppress(DeviceError):
                    await asyncio.shield(self.xray_off())
                raise
            if hold_s is not None:
                self._hold_task = asyncio.ensure_future(self._off_after(hold_s))
            return result

    async def _off_after(self, hold_s: float) -> None:
        await asyncio.sleep(hold_s)
        self._hold_sending = True  # from here on the request runs to its reply: it is never cut short
        try:
            await self._request("xray off (nothing exposing)", self._xray_off_call)
        except DeviceError as exc:  # the generator's own watchdog still switches it off once the heartbeat stops
            log.error(
                "%s: could not switch high voltage off after %.3g s without an exposure: %s", self.name, hold_s, exc
            )
        finally:
            self._hold_sending = False

    async def _cancel_hold(self) -> None:
        """End the hold: cancelled while it still waits; once its X-rays-off request is on the wire, let it finish."""
        task, self._hold_task = self._hold_task, None
        if task is None or task.done() or task is asyncio.current_task():
            return
        if self._hold_sending:
            with contextlib.suppress(Exception):
                await asyncio.shield(task)
            return
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    def _xray_off_call(self, c: AsyncModbusTcpClient) -> Awaitable[Any]:
        return c.write_coils(reg.PREP_REQ, [False, False, True], device_id=self.device_id)

    async def xray_off(self) -> None:
        """Drop prep and expose requests and switch high voltage off (safe in every state)."""
        await self._cancel_hold()
        await self._request("xray off", self._xray_off_call)

    async def reset_fault(self) -> None:
        """Clear a fault whose cause is gone; raises naming the cause while the generator stays in FAULT."""
        await self._write_coil(reg.FAULT_RESET, True)
        ir = await self._read_input_registers()
        if ir[reg.STATE] == GeneratorState.FAULT:
            di = await self._read_inputs()
            cause = (
                "the door interlock is still open"
                if not di[reg.DOOR_CLOSED]
                else "its cause is still present (the generator's fault input is asserted)"
            )
            raise FaultActiveError(f"{self.name}: {self._fault_text(ir[reg.FAULT_CODE])} was not reset: {cause}")
        self._link_fault = None
