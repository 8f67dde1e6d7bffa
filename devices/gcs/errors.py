"""PI GCS 2.0 controller error codes (as in PI's GCS error list) and their named exceptions."""

from __future__ import annotations

from devices.errors import ControllerError, NotReferencedError, OutOfLimitsError

# code -> PI's meaning; the twin reports these and the client turns them into exceptions
GCS_ERRORS: dict[int, str] = {
    0: "No error",
    1: "Parameter syntax error",
    2: "Unknown command",
    3: "Command length out of limits or command buffer overrun",
    5: "Unallowable move attempted on unreferenced axis, or move attempted with servo off",
    7: "Position out of limits",
    8: "Velocity out of limits",
    9: "Attempt to set pivot point while U,V and W not all 0",
    10: "Controller was stopped by command",
    15: "Invalid axis identifier",
    17: "Parameter out of range",
    22: "Axis identifier specified more than once",
    23: "Illegal axis or channel",
    24: "Incorrect number of parameters",
    25: "Invalid floating point number",
    26: "Parameter missing",
    89: "Command not allowed in current motion mode",
    93: "This command is not allowed while the affected axis or its master is in motion",
}

PARAM_SYNTAX = 1
UNKNOWN_COMMAND = 2
MOVE_WITHOUT_REF_OR_NO_SERVO = 5
POS_OUT_OF_LIMITS = 7
PIVOT_NOT_POSSIBLE = 9
STOPPED = 10
INVALID_AXIS = 15
PARAM_OUT_OF_RANGE = 17
ILLEGAL_AXIS = 23
PARAM_NR = 24
NOT_ALLOWED_IN_MOTION_MODE = 89
NOT_ALLOWED_WHILE_MOVING = 93


class GcsOutOfLimitsError(ControllerError, OutOfLimitsError):
    """The controller refused a target as out of limits (GCS error 7)."""


class GcsNotReferencedError(ControllerError, NotReferencedError):
    """The controller refused a move: axis unreferenced or servo off (GCS error 5)."""


def error_text(code: int) -> str:
    """PI's text for an error code (or a generic one for codes outside the table)."""
    return GCS_ERRORS.get(int(code), f"controller error {int(code)} (see the controller manual)")


def controller_error(code: int, command: str = "") -> ControllerError:
    """The named exception for a non-zero GCS error code raised after ``command``."""
    text = error_text(code)
    if code == POS_OUT_OF_LIMITS:
        return GcsOutOfLimitsError(code, text, command)
    if code == MOVE_WITHOUT_REF_OR_NO_SERVO:
        return GcsNotReferencedError(code, text, command)
    return ControllerError(code, text, command)
