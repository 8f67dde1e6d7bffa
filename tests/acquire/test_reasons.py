"""Why a scan ended, as the operator reads it: what happened and what to do, never an exception's class name."""

from __future__ import annotations

import asyncio

import pytest

from acquire.errors import AcquireError
from acquire.reasons import abort_reason, is_expected
from devices.errors import (
    ControllerError,
    DeviceError,
    DeviceTimeoutError,
    InterlockOpenError,
    NotConnectedError,
    ProtocolError,
)

CASES = [
    (InterlockOpenError("xray: the door interlock is open"), "close the X-ray room door"),
    (NotConnectedError("hexapod: connection lost"), "check the device's power and cable"),
    (DeviceTimeoutError("rotation stage: no reply within 1 s"), "check that the device is on and answering"),
    (ProtocolError("detector: garbled reply"), "check the cable and the device's address"),
    (ControllerError(10, "Controller was stopped by command", "MOV"), "look up the error code"),
    (DeviceError("panel: something else"), "check the device"),
]


@pytest.mark.parametrize(("exc", "advice"), CASES)
def test_a_device_failure_reads_as_what_happened_and_what_to_do(exc: DeviceError, advice: str) -> None:
    reason = abort_reason(exc)
    assert reason.startswith(str(exc)) and advice in reason
    assert type(exc).__name__ not in reason and "Error" not in reason
    assert is_expected(exc)


def test_an_unexpected_failure_says_so_without_its_class_name() -> None:
    reason = abort_reason(ZeroDivisionError("float division by zero"))
    assert "failed unexpectedly (float division by zero)" in reason and "please report it" in reason
    assert "ZeroDivisionError" not in reason and not is_expected(ZeroDivisionError())
    assert "no message" in abort_reason(RuntimeError())


def test_interruptions_and_refusals_keep_their_own_words() -> None:
    assert abort_reason(KeyboardInterrupt()) == "interrupted by the user (Ctrl-C)"
    assert abort_reason(asyncio.CancelledError()) == "cancelled"
    assert abort_reason(AcquireError("stall: detector delivered no frame in 5 s")) == (
        "stall: detector delivered no frame in 5 s"
    )


def test_a_disk_that_fills_under_the_scan_file_reads_as_a_full_disk_not_a_bug() -> None:
    """The scan file refuses a frame it cannot write and still close cleanly; when the disk fills between the
    recorder's checks that refusal ends the scan, and it said "orbitct failed unexpectedly ... please report it"."""
    from orbitct.scanfile import DiskFullError

    exc = DiskFullError("scans/a.h5: frame 5 not written: 916 kB free, 1.1 MB needed to write it and close the file")
    said = abort_reason(exc)
    assert said.startswith("the data disk is full (scans/a.h5: frame 5 not written: 916 kB free")
    assert said.endswith("free space on it, then scan again") and "unexpectedly" not in said and is_expected(exc)
