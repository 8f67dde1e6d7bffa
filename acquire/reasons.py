"""Why a scan ended, in words an operator can act on: what happened and what to do, never an exception's class."""

from __future__ import annotations

import asyncio

from acquire.errors import AcquireError
from devices.errors import (
    ControllerError,
    DeviceError,
    DeviceTimeoutError,
    FaultActiveError,
    InterlockOpenError,
    NotConnectedError,
    NotReferencedError,
    OutOfLimitsError,
    ProtocolError,
)
from orbitct.scanfile import DiskFullError

#: what an operator does next, per kind of device failure (the first that matches applies)
ADVICE: tuple[tuple[type[DeviceError], str], ...] = (
    (InterlockOpenError, "close the X-ray room door, then start the scan again"),
    (FaultActiveError, "clear the fault on the device, reset the stop, then start the scan again"),
    (NotConnectedError, "check the device's power and cable, then start the scan again"),
    (DeviceTimeoutError, "check that the device is on and answering, then start the scan again"),
    (ProtocolError, "check the cable and the device's address, then start the scan again"),
    (ControllerError, "look up the error code in the controller's manual, then start the scan again"),
    (OutOfLimitsError, "choose an orbit inside the travel ranges"),
    (NotReferencedError, "reference the axes (orbitct reference), then start the scan again"),
    (DeviceError, "check the device, then start the scan again"),
)


def abort_reason(exc: BaseException) -> str:
    """One sentence on why a scan ended on ``exc``, with what to do next."""
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted by the user (Ctrl-C)"
    if isinstance(exc, asyncio.CancelledError):
        return "cancelled"
    text = str(exc).strip()
    if isinstance(exc, AcquireError):
        return text or "the scan could not go on"
    if isinstance(exc, DeviceError):
        advice = next(a for kind, a in ADVICE if isinstance(exc, kind))
        return f"{text or 'a device failed'}; {advice}"
    if isinstance(exc, DiskFullError):  # the scan file's own guard, when the disk filled between two checks
        return f"the data disk is full ({text or 'no room for the next frame'}); free space on it, then scan again"
    return (
        f"orbitct failed unexpectedly ({text or 'no message'}); the scan was stopped; "
        "the log has the details: please report it"
    )


def is_expected(exc: BaseException) -> bool:
    """Whether ``exc`` is a failure the bench can have (a device's, a refusal), not a fault of orbitct's own."""
    return isinstance(exc, (AcquireError, DeviceError, DiskFullError, KeyboardInterrupt, asyncio.CancelledError))
