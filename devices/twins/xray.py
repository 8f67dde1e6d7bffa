"""X-ray generator twin: a pymodbus TCP server with the generator's state machine and timing.

It speaks the register map of :mod:`devices.xray_registers`, drives ``SimWorld.exposing``
and the world's X-ray settings, and counts completed exposures in the world so the detector
twin can trigger on them. Faults (latency, dropped connection, garbled reply, device error,
missing frame) and hazards (open door, generator fault) are injected on request.

Also home of :class:`TwinFaults` and :class:`TwinThread`, shared by every twin in this package.
"""

from __future__ import annotations

import asyncio
import functools
import time
from collections import deque
from typing import Any, ClassVar

try:
    from pymodbus.constants import ExcCodes
except ImportError:  # pymodbus < 3.11 names no exception codes: same numbers, own enum
    import enum

    class ExcCodes(enum.IntEnum):  # type: ignore[no-redef]
        ILLEGAL_VALUE = 3
        DEVICE_FAILURE = 4
        DEVICE_BUSY = 6


from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusTcpServer

from devices import xray_registers as reg
from devices.twins.runtime import TwinFaults, garble
from devices.twins.world import SimWorld, get_world
from devices.xray_registers import FaultCode, GeneratorState, Refusal

HEARTBEAT_PERIOD_S = 0.1
HV_STATES = (GeneratorState.PREP, GeneratorState.READY, GeneratorState.EXPOSING, GeneratorState.DONE)


def _bits_to_registers(bits: list[bool]) -> list[int]:
    bits = bits + [False] * (-len(bits) % 16)
    return [sum(1 << i for i, b in enumerate(bits[k : k + 16]) if b) for k in range(0, len(bits), 16)]


class _GeneratorServer(ModbusTcpServer):
    """pymodbus's Modbus TCP server, answering each connection's requests one at a time in the order they came, each
    with its own transaction id, as the generator's controller does. pymodbus's own handler (3.16 at least)
    labels every reply with the newest request's id: a request that waits (the latency fault) while the client sends
    the next one (the first cut short) was answered under the second one's id."""

    def callback_new_connection(self) -> Any:
        handler = super().callback_new_connection()
        if hasattr(ModbusPDU, "datastore_update") and all(
            hasattr(handler, name) for name in ("handle_request", "last_pdu", "last_addr", "server_send")
        ):
            handler.handle_request = functools.partial(_answer_in_order, handler, asyncio.Lock())
        return handler


async def _answer_in_order(handler: Any, turn: asyncio.Lock) -> None:
    """Answer the request ``handler`` has just received, after those before it (``turn``), under its own id."""
    pdu, addr = handler.last_pdu, handler.last_addr
    if pdu is None:
        return
    async with turn:
        try:
            response = await pdu.datastore_update(handler.server.context, pdu.dev_id)
        except Exception:  # noqa: BLE001 - as pymodbus does: the client hears a device failure
            response = ExceptionResponse(pdu.function_code, ExcCodes.DEVICE_FAILURE)
        response.transaction_id, response.dev_id = pdu.transaction_id, pdu.dev_id
        handler.server_send(response, addr)


class XrayTwin:
    """Simulated X-ray generator served over Modbus TCP with the documented register map."""

    scheme: ClassVar[str] = "modbus"

    def __init__(
        self,
        world: SimWorld | None = None,
        *,
        prep_s: float = 0.2,
        time_scale: float = 1.0,
        model: str = "SimGen XR-150",
        serial: str = "XG-0001",
        firmware: int = 102,
    ) -> None:
        self.world = world if world is not None else get_world("bench")
        self.prep_s = prep_s
        self.time_scale = time_scale  # simulated seconds per wall-clock second (10 = ten times faster)
        self.faults = TwinFaults()
        self.model, self.serial, self.firmware = model, serial, firmware
        self._state = GeneratorState.IDLE
        self._state_since = time.monotonic()
        self.hv_on_s = 0.0  # wall-clock seconds with high voltage on (PREP, READY, EXPOSING, DONE), completed intervals
        self.exposing_s = 0.0  # of which exposing
        self.fault_code = FaultCode.NONE
        self.refusal = Refusal.NONE
        self.door_closed = True
        self.prep_req = False
        self.expose_req = False
        self.kv_set, self.ma_set, self.exposure_ms = 90.0, 1.0, 10
        self.watchdog_ms = reg.WATCHDOG_MS_DEFAULT
        self.heartbeat_in = 0
        self.heartbeat_out = 0
        self.frame_counter = 0
        self.last_exposure_ms = 0
        self._last_hb = time.monotonic()
        self._timer: asyncio.TimerHandle | None = None
        self._exposure_t0 = 0.0
        self._server: ModbusTcpServer | None = None
        self._ticker: asyncio.Task[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.requests = 0
        self.request_log: deque[str] = deque(maxlen=1000)  # "fc<code>:<address>[=<values>]" of recent requests
        self.heartbeat_frozen = False  # hazard on request: the generator's own heartbeat stops
        self.fault_input = (
            False  # hazard on request: the fault input stays asserted (overtemperature): no reset clears it
        )

    # ------------------------------------------------------------ dose bookkeeping
    @property
    def state(self) -> GeneratorState:
        """The generator's state (``STATE`` input register)."""
        return self._state

    @state.setter
    def state(self, new: GeneratorState) -> None:
        now = time.monotonic()
        if self._state in HV_STATES:
            self.hv_on_s += now - self._state_since
        if self._state == GeneratorState.EXPOSING:
            self.exposing_s += now - self._state_since
        self._state, self._state_since = GeneratorState(new), now

    def dose_seconds(self) -> tuple[float, float]:
        """Wall-clock seconds so far with high voltage on, and of those exposing (the current interval included)."""
        open_s = time.monotonic() - self._state_since
        hv = self.hv_on_s + (open_s if self._state in HV_STATES else 0.0)
        return hv, self.exposing_s + (open_s if self._state == GeneratorState.EXPOSING else 0.0)

    # ----------------------------------------------------------------- serving
    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen on ``host:port`` (0 = any free port); returns the port."""
        self._loop = asyncio.get_running_loop()
        self._server = _GeneratorServer(self._datastore(), address=(host, port), trace_packet=self._trace_packet)
        await self._server.serve_forever(background=True)
        sockets = self._server.transport.sockets  # type: ignore[attr-defined]
        self._ticker = asyncio.ensure_future(self._tick())
        return int(sockets[0].getsockname()[1])

    async def stop(self) -> None:
        """Switch X-rays off and close the server."""
        self._hv_off()
        if self._ticker is not None:
            self._ticker.cancel()
        if self._server is not None:
            await self._server.shutdown()
            self._server = None

    @property
    def connections(self) -> int:
        """How many clients are connected now (read it in the twin's loop)."""
        return 0 if self._server is None else len(self._server.active_connections)

    def drop_connections(self) -> None:
        """Close every client connection now (as a pulled cable would)."""
        if self._server is None:
            return
        for conn in list(self._server.active_connections.values()):
            if conn.transport is not None:
                conn.transport.abort()  # type: ignore[attr-defined]

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if sending and self.faults.take("garble"):
            return garble(data, len(data) // 2)  # the second half: the header still names the transaction
        if sending and len(data) > 7 and data[7] in (3, 4) and self.faults.take("misanswer"):
            return (
                data[:7] + bytes([7 - data[7]]) + data[8:]
            )  # function 3 <-> 4: a well-formed reply to another request
        return data

    # ------------------------------------------------------- hazards on request
    def set_door(self, closed: bool) -> None:
        """Close or open the door interlock (call from the twin's loop or via TwinThread.call)."""
        self.door_closed = bool(closed)
        if closed:
            return
        if self.state == GeneratorState.EXPOSING:
            self._enter_fault(FaultCode.INTERLOCK_OPENED)
        elif self.state in (GeneratorState.PREP, GeneratorState.READY, GeneratorState.DONE):
            self._hv_off()
            self.state = GeneratorState.IDLE
            self.refusal = Refusal.INTERLOCK_OPEN

    def raise_fault(self, code: FaultCode = FaultCode.GENERATOR) -> None:
        """Enter FAULT with ``code`` (high voltage off, any exposure lost)."""
        self._enter_fault(FaultCode(code))

    def set_fault_input(self, active: bool) -> None:
        """Assert (a GENERATOR fault that no reset clears) or release the generator's fault input."""
        self.fault_input = bool(active)
        if active:
            self._enter_fault(FaultCode.GENERATOR)

    # ---------------------------------------------------------- state machine
    def _enter_fault(self, code: FaultCode) -> None:
        self._hv_off()
        self.state = GeneratorState.FAULT
        self.fault_code = code

    def _hv_off(self) -> None:
        self.prep_req = self.expose_req = False  # requests are dropped whenever high voltage goes off
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        with self.world.lock:
            self.world.exposing = False

    def _refuse(self, why: Refusal) -> None:
        self.refusal = why

    def _blocked(self) -> bool:
        if self.state == GeneratorState.FAULT:
            self._refuse(Refusal.FAULT_ACTIVE)
            return True
        if not self.door_closed:
            self._refuse(Refusal.INTERLOCK_OPEN)
            return True
        return False

    def _set_prep(self, on: bool) -> None:
        self.prep_req = on
        if not on:
            if self.state in (GeneratorState.PREP, GeneratorState.READY, GeneratorState.EXPOSING, GeneratorState.DONE):
                self._hv_off()
                self.state = GeneratorState.IDLE
            return
        if self._blocked():
            self.prep_req = False
            return
        if self.state == GeneratorState.IDLE:
            self.refusal = Refusal.NONE
            self._last_hb = time.monotonic()
            self.state = GeneratorState.PREP
            assert self._loop is not None
            self._timer = self._loop.call_later(self.prep_s / self.time_scale, self._prep_done)

    def _prep_done(self) -> None:
        self._timer = None
        if self.state == GeneratorState.PREP:
            self.state = GeneratorState.READY

    def _set_expose(self, on: bool) -> None:
        self.expose_req = on
        if not on:
            if self.state == GeneratorState.DONE:
                self.state = GeneratorState.READY if self.prep_req else GeneratorState.IDLE
            return
        if self._blocked():
            self.expose_req = False
            return
        if self.state != GeneratorState.READY:
            self._refuse(Refusal.NOT_READY)
            self.expose_req = False
            return
        self.refusal = Refusal.NONE
        self.state = GeneratorState.EXPOSING
        self._exposure_t0 = time.monotonic()
        with self.world.lock:
            self.world.xray_kv, self.world.xray_ma = self.kv_set, self.ma_set
            self.world.exposure_ms = float(self.exposure_ms)
            self.world.exposing = True
        assert self._loop is not None
        self._timer = self._loop.call_later(self.exposure_ms / 1000.0 / self.time_scale, self._exposure_done)

    def _exposure_done(self) -> None:
        self._timer = None
        if self.state != GeneratorState.EXPOSING:
            return
        self.last_exposure_ms = int(round((time.monotonic() - self._exposure_t0) * 1000 * self.time_scale))
        lost = self.faults.take("missing_frame")
        with self.world.lock:
            self.world.exposing = False
            if not lost:
                self.world.xray_frame_counter += 1
        if not lost:
            self.frame_counter += 1
        self.state = GeneratorState.DONE

    def _xray_off(self) -> None:
        self.prep_req = self.expose_req = False
        if self.state != GeneratorState.FAULT:
            self.state = GeneratorState.IDLE
        self._hv_off()

    def _fault_reset(self) -> None:
        if self.state != GeneratorState.FAULT:
            return
        if self.fault_code == FaultCode.INTERLOCK_OPENED and not self.door_closed:
            self._refuse(Refusal.INTERLOCK_OPEN)
            return
        if self.fault_input:
            self._refuse(Refusal.FAULT_ACTIVE)
            return
        self.state = GeneratorState.IDLE
        self.fault_code = FaultCode.NONE

    async def _tick(self) -> None:
        while True:
            await asyncio.sleep(HEARTBEAT_PERIOD_S)
            if not self.heartbeat_frozen:
                self.heartbeat_out = (self.heartbeat_out + 1) & 0xFFFF
            if (
                self.state in HV_STATES
                and self.watchdog_ms
                and time.monotonic() - self._last_hb > self.watchdog_ms / 1000.0
            ):
                self._enter_fault(FaultCode.WATCHDOG)

    # ------------------------------------------------------------ registers
    def _coils(self) -> list[bool]:
        return [self.prep_req, self.expose_req, False, False]

    def _inputs(self) -> list[bool]:
        s = self.state
        hv = s in (GeneratorState.PREP, GeneratorState.READY, GeneratorState.EXPOSING)
        return [
            self.door_closed,
            s == GeneratorState.READY,
            s == GeneratorState.EXPOSING,
            s == GeneratorState.FAULT,
            hv,
        ]

    def _holding(self) -> list[int]:
        return [
            int(round(self.kv_set * reg.KV_SCALE)),
            int(round(self.ma_set * reg.MA_SCALE)),
            int(self.exposure_ms),
            self.heartbeat_in,
            int(self.watchdog_ms),
        ]

    def _input_registers(self) -> list[int]:
        hv = self.state in (GeneratorState.PREP, GeneratorState.READY, GeneratorState.EXPOSING)
        out = [0] * reg.N_INPUT_REGS
        out[reg.STATE] = int(self.state)
        out[reg.FAULT_CODE] = int(self.fault_code)
        out[reg.FRAME_COUNTER_HI] = (self.frame_counter >> 16) & 0xFFFF
        out[reg.FRAME_COUNTER_LO] = self.frame_counter & 0xFFFF
        out[reg.HEARTBEAT_OUT] = self.heartbeat_out
        out[reg.KV_ACTUAL] = int(round(self.kv_set * reg.KV_SCALE)) if hv else 0
        out[reg.MA_ACTUAL] = int(round(self.ma_set * reg.MA_SCALE)) if self.state == GeneratorState.EXPOSING else 0
        out[reg.LAST_EXPOSURE_MS] = self.last_exposure_ms
        out[reg.REFUSAL] = int(self.refusal)
        out[reg.FIRMWARE] = self.firmware
        out[reg.MODEL : reg.MODEL + reg.TEXT_REGISTERS] = reg.text_to_registers(self.model)
        out[reg.SERIAL : reg.SERIAL + reg.TEXT_REGISTERS] = reg.text_to_registers(self.serial)
        return out

    def _write_holding(self, address: int, values: list[int]) -> ExcCodes | None:
        new = dict(enumerate(self._holding()))
        for i, v in enumerate(values):
            new[address + i] = int(v)
        kv, ma = new[reg.KV_SET] / reg.KV_SCALE, new[reg.MA_SET] / reg.MA_SCALE
        if not (reg.KV_RANGE[0] <= kv <= reg.KV_RANGE[1] and reg.MA_RANGE[0] <= ma <= reg.MA_RANGE[1]):
            return ExcCodes.ILLEGAL_VALUE
        if not reg.EXPOSURE_MS_RANGE[0] <= new[reg.EXPOSURE_MS] <= reg.EXPOSURE_MS_RANGE[1]:
            return ExcCodes.ILLEGAL_VALUE
        if new[reg.WATCHDOG_MS] and not 100 <= new[reg.WATCHDOG_MS] <= 60000:
            return ExcCodes.ILLEGAL_VALUE
        settings_changed = (kv, ma, new[reg.EXPOSURE_MS]) != (self.kv_set, self.ma_set, self.exposure_ms)
        if settings_changed and self.state == GeneratorState.EXPOSING:
            return ExcCodes.DEVICE_BUSY
        self.kv_set, self.ma_set, self.exposure_ms = kv, ma, new[reg.EXPOSURE_MS]
        if settings_changed:  # the technique the panel's open-beam (flat) frames see from now on, as a real source's
            with self.world.lock:
                self.world.xray_kv, self.world.xray_ma = self.kv_set, self.ma_set
                self.world.exposure_ms = float(self.exposure_ms)
        self.watchdog_ms = new[reg.WATCHDOG_MS]
        if new[reg.HEARTBEAT_IN] != self.heartbeat_in or reg.HEARTBEAT_IN in range(address, address + len(values)):
            self._last_hb = time.monotonic()
        self.heartbeat_in = new[reg.HEARTBEAT_IN]
        return None

    def _write_coils(self, address: int, values: list[bool]) -> None:
        for i, v in enumerate(values):
            coil = address + i
            if coil == reg.PREP_REQ and bool(v) != self.prep_req:
                self._set_prep(bool(v))
            elif coil == reg.EXPOSE_REQ and bool(v) != self.expose_req:
                self._set_expose(bool(v))
            elif coil == reg.XRAY_OFF and v:
                self._xray_off()
            elif coil == reg.FAULT_RESET and v:
                self._fault_reset()

    def _block(self, function_code: int) -> list[int] | list[bool]:
        """Live values of the table a function code addresses."""
        if function_code in (1, 5, 15):
            return self._coils()
        if function_code == 2:
            return self._inputs()
        if function_code in (3, 6, 16):
            return self._holding()
        return self._input_registers()

    async def _request(
        self, function_code: int, address: int, values: list[int] | list[bool] | None
    ) -> ExcCodes | None:
        """Faults first, then a write's effect; an exception code refuses the request."""
        self.requests += 1
        request = f"fc{function_code}:{address}" + ("" if values is None else f"={[int(v) for v in values]}")
        self.request_log.append(request)
        if self.faults.latency_s > 0:
            await asyncio.sleep(self.faults.latency_s)
        if self.faults.take("drop", request):
            self.drop_connections()
            return None
        if self.faults.take("error", request):
            return ExcCodes.DEVICE_FAILURE
        if values is not None and function_code in (5, 15):
            self._write_coils(address, [bool(v) for v in values])
        elif values is not None and function_code in (6, 16):
            return self._write_holding(address, [int(v) for v in values])
        return None

    def _datastore(self) -> Any:
        """What ModbusTcpServer serves: a SimDevice with an action (pymodbus >= 3.13) or a device context (3.10-3.12)."""
        try:
            from pymodbus.datastore import ModbusBaseDeviceContext, ModbusServerContext  # type: ignore[attr-defined]
        except ImportError:
            from pymodbus.simulator import DataType, SimData, SimDevice

            bits, regs = DataType.BITS, DataType.REGISTERS
            blocks = (
                [SimData(0, count=16, values=False, datatype=bits)],
                [SimData(0, count=16, values=False, datatype=bits)],
                [SimData(0, count=reg.N_HOLDING, values=0, datatype=regs)],
                [SimData(0, count=reg.N_INPUT_REGS, values=0, datatype=regs)],
            )
            return SimDevice(id=0, simdata=blocks, action=self._action)
        twin = self

        class _Device(ModbusBaseDeviceContext):
            async def async_getValues(self, fc: int, address: int, count: int = 1) -> list[int] | list[bool]:
                if fc in (1, 2, 3, 4) and await twin._request(fc, address, None):
                    raise DeviceFailure(f"injected device error on function {fc}")
                block = twin._block(fc)
                if address < 0 or address + count > len(block):
                    raise DeviceFailure(f"address {address}+{count} outside the table")
                return block[address : address + count]

            async def async_setValues(self, fc: int, address: int, values: list[int] | list[bool]) -> int | None:
                result = await twin._request(fc, address, list(values))
                return int(result) if result else None

        return ModbusServerContext(devices=_Device(), single=True)

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        result = await self._request(function_code, address, set_values)
        if result is not None:
            return result
        # refresh the whole table so that the reply (and stored bits) show the live state
        live = self._block(function_code)
        if function_code in (1, 2, 5, 15):
            registers[:2] = _bits_to_registers(list(live)) + [0]  # type: ignore[arg-type]
        else:
            registers[: len(live)] = live
        return None


class DeviceFailure(Exception):
    """Raised inside the legacy datastore: pymodbus answers with exception code 4 (device failure)."""
