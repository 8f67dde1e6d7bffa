"""Named device errors: every driver raises one of these, never a bare exception."""

from __future__ import annotations


class DeviceError(Exception):
    """Base of all device errors."""


class NotConnectedError(DeviceError):
    """The device is not connected (or the connection was lost)."""


class OutOfLimitsError(DeviceError):
    """A target lies outside the travel range or workspace; nothing moved."""


class NotReferencedError(DeviceError):
    """An axis must be referenced before it may move."""


class DeviceTimeoutError(DeviceError):
    """No reply, or no completion, within the allowed time."""


class ControllerError(DeviceError):
    """The controller reported an error code."""

    def __init__(self, code: int, text: str, command: str = "") -> None:
        self.code = int(code)
        self.text = text
        self.command = command
        where = f" after {command!r}" if command else ""
        super().__init__(f"controller error {self.code}{where}: {text}")


class InterlockOpenError(DeviceError):
    """The X-ray door interlock is open; nothing was exposed."""


class FaultActiveError(DeviceError):
    """The device is in a fault state; clear the fault first."""


class ProtocolError(DeviceError):
    """A reply could not be parsed (garbled, truncated or unexpected)."""


class UriError(DeviceError, ValueError):
    """A device URI that cannot be used; the message says what is allowed."""
