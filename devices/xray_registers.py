"""Modbus TCP register map of the X-ray generator (driver and twin share it).

Addresses are 0-based protocol addresses (what goes on the wire); device id 1.
Scaled values are unsigned 16-bit integers; 32-bit counters are two registers,
high word first.

Coils (FC1 read, FC5/FC15 write) - requests from orbitct:

| addr | name          | meaning                                                         |
| ---- | ------------- | --------------------------------------------------------------- |
| 0    | PREP_REQ      | 1 = prepare (rotor up, filament boost); held while exposing     |
| 1    | EXPOSE_REQ    | 1 = expose once (only honoured in READY); drop it after DONE    |
| 2    | XRAY_OFF      | write 1 = high voltage off now, requests cleared (self-clearing) |
| 3    | FAULT_RESET   | write 1 = clear a fault whose cause is gone (self-clearing)     |

Discrete inputs (FC2) - acknowledgements and inputs of the generator:

| addr | name          | meaning                                                         |
| ---- | ------------- | --------------------------------------------------------------- |
| 0    | DOOR_CLOSED   | door interlock chain closed (1 = safe to expose)                |
| 1    | READY_ACK     | state is READY                                                  |
| 2    | EXPOSING_ACK  | state is EXPOSING (the detector's hardware trigger)             |
| 3    | FAULT_ACTIVE  | state is FAULT                                                  |
| 4    | HV_ON         | high voltage on (PREP, READY or EXPOSING)                       |

Holding registers (FC3 read, FC6/FC16 write) - settings:

| addr | name          | unit / scale         | range                                  |
| ---- | ------------- | -------------------- | -------------------------------------- |
| 0    | KV_SET        | 0.1 kV               | 400..1500 (40.0..150.0 kV)             |
| 1    | MA_SET        | 0.01 mA              | 1..50000 (0.01..500.00 mA)             |
| 2    | EXPOSURE_MS   | ms                   | 1..10000                               |
| 3    | HEARTBEAT_IN  | counter              | orbitct writes a changing value        |
| 4    | WATCHDOG_MS   | ms                   | 0 (off) or 100..60000; default 2000    |

Input registers (FC4) - state read back:

| addr | name          | unit / scale         | meaning                                 |
| ---- | ------------- | -------------------- | --------------------------------------- |
| 0    | STATE         | enum                 | 0 IDLE, 1 PREP, 2 READY, 3 EXPOSING, 4 DONE, 5 FAULT |
| 1    | FAULT_CODE    | enum                 | see :class:`FaultCode`                  |
| 2-3  | FRAME_COUNTER | uint32 (high first)  | completed exposures since power-on      |
| 4    | HEARTBEAT_OUT | counter              | generator increments it every 100 ms    |
| 5    | KV_ACTUAL     | 0.1 kV               | tube voltage now (0 when HV off)        |
| 6    | MA_ACTUAL     | 0.01 mA              | tube current now (0 unless exposing)    |
| 7    | LAST_EXPOSURE_MS | ms                | duration of the last completed exposure |
| 8    | REFUSAL       | enum                 | why the last request was refused, see :class:`Refusal` |
| 9    | FIRMWARE      | major*100 + minor    |                                         |
| 16-23| MODEL         | 16 ASCII chars       | space padded                            |
| 24-31| SERIAL        | 16 ASCII chars       | space padded                            |

State machine: IDLE --PREP_REQ--> PREP --(prep time)--> READY --EXPOSE_REQ--> EXPOSING
--(exposure time)--> DONE (FRAME_COUNTER + 1). From DONE, dropping EXPOSE_REQ returns to
READY if PREP_REQ is still held, else to IDLE. Dropping PREP_REQ in PREP or READY returns
to IDLE. Requests are refused (state unchanged, REFUSAL set, nothing exposed) while the door
is open or a fault is active. The door opening during an exposure, a heartbeat older than
WATCHDOG_MS while high voltage is on, or a generator fault moves to FAULT (high voltage off).
"""

from __future__ import annotations

import enum

DEVICE_ID = 1

# coils
PREP_REQ, EXPOSE_REQ, XRAY_OFF, FAULT_RESET = 0, 1, 2, 3
N_COILS = 4

# discrete inputs
DOOR_CLOSED, READY_ACK, EXPOSING_ACK, FAULT_ACTIVE, HV_ON = 0, 1, 2, 3, 4
N_INPUTS = 5

# holding registers
KV_SET, MA_SET, EXPOSURE_MS, HEARTBEAT_IN, WATCHDOG_MS = 0, 1, 2, 3, 4
N_HOLDING = 5

# input registers
STATE, FAULT_CODE, FRAME_COUNTER_HI, FRAME_COUNTER_LO, HEARTBEAT_OUT = 0, 1, 2, 3, 4
KV_ACTUAL, MA_ACTUAL, LAST_EXPOSURE_MS, REFUSAL, FIRMWARE = 5, 6, 7, 8, 9
MODEL, SERIAL = 16, 24
TEXT_REGISTERS = 8
N_INPUT_REGS = 32

KV_SCALE = 10.0
MA_SCALE = 100.0
KV_RANGE = (40.0, 150.0)
MA_RANGE = (0.01, 500.0)
EXPOSURE_MS_RANGE = (1, 10000)
WATCHDOG_MS_DEFAULT = 2000


class GeneratorState(enum.IntEnum):
    """Value of the STATE input register."""

    IDLE = 0
    PREP = 1
    READY = 2
    EXPOSING = 3
    DONE = 4
    FAULT = 5


class FaultCode(enum.IntEnum):
    """Value of the FAULT_CODE input register."""

    NONE = 0
    INTERLOCK_OPENED = 1  # door opened while high voltage was on during an exposure
    WATCHDOG = 2  # heartbeat from orbitct stopped while high voltage was on
    GENERATOR = 3  # internal generator fault (arc, overtemperature)
    INVALID_SETTINGS = 4  # kV/mA/exposure out of range at prepare


class Refusal(enum.IntEnum):
    """Value of the REFUSAL input register: why the last request did nothing."""

    NONE = 0
    INTERLOCK_OPEN = 1
    FAULT_ACTIVE = 2
    NOT_READY = 3
    INVALID_SETTINGS = 4


MODBUS_EXCEPTIONS = {
    1: "ILLEGAL_FUNCTION",
    2: "ILLEGAL_ADDRESS",
    3: "ILLEGAL_VALUE",  # a setting out of range
    4: "DEVICE_FAILURE",
    5: "ACKNOWLEDGE",
    6: "DEVICE_BUSY",  # settings changed during an exposure
    10: "GATEWAY_PATH_UNAVAILABLE",
    11: "GATEWAY_NO_RESPONSE",
}


def text_to_registers(text: str) -> list[int]:
    """Pack ASCII text into :data:`TEXT_REGISTERS` registers (space padded, 2 chars each)."""
    raw = text.encode("ascii", "replace")[: 2 * TEXT_REGISTERS].ljust(2 * TEXT_REGISTERS, b" ")
    return [int.from_bytes(raw[i : i + 2], "big") for i in range(0, len(raw), 2)]


def registers_to_text(regs: list[int]) -> str:
    """Unpack ASCII text packed by :func:`text_to_registers`."""
    return b"".join(int(r).to_bytes(2, "big") for r in regs).decode("ascii", "replace").strip()
