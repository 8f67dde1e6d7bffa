"""The catalogue of errors a person can meet in the CLI and the API: a stable code for scripts, the exit status and
HTTP status it comes with, what it means and what to do when nothing more precise is known.

Every error reads ``<what happened>; <what to do>``: the API sends it as ``message`` with ``error`` (the code) and
``advice`` (the part after the semicolon); the CLI prints ``error [code]: message`` on stderr and exits with the
code's exit status. The documentation's error page is made from this table.
"""

from __future__ import annotations

import errno
from dataclasses import dataclass


@dataclass(frozen=True)
class ErrorKind:
    """One entry of the catalogue."""

    code: str
    meaning: str  # when it happens, for the documentation
    advice: str  # what to do, where the place that raised it knows nothing more precise
    exit_status: int | None = None  # the CLI's exit status; None: the CLI never reports it
    http_status: int | None = None  # the API's status; None: the API never reports it


CATALOGUE: dict[str, ErrorKind] = {
    k.code: k
    for k in (
        ErrorKind(
            "invalid_parameters",
            "a value given is missing, malformed or out of range (an option, a field, a configuration or input file)",
            "correct the value named and try again",
            exit_status=2,
            http_status=422,
        ),
        ErrorKind(
            "bad_request",
            "the request body cannot be read (not UTF-8 JSON, or the wrong content type)",
            "send UTF-8 JSON with Content-Type: application/json (GET /docs shows each route's body)",
            http_status=400,
        ),
        ErrorKind(
            "unauthorized",
            "no valid sign-in came with the request (no token, an unknown token, an expired session)",
            "sign in at /sign-in, or send a token an operator made for you (Authorization: Bearer TOKEN)",
            exit_status=2,
            http_status=401,
        ),
        ErrorKind(
            "forbidden",
            "the person signed in does not have the role this needs",
            "ask an operator to give you the role named (the console's People page, or orbitct token create --role)",
            exit_status=2,
            http_status=403,
        ),
        ErrorKind(
            "not_found",
            "no scan, job, file or name like the one given",
            "check the id or path (GET /scans, /calibrations and /reconstructions list what exists)",
            exit_status=2,
            http_status=404,
        ),
        ErrorKind(
            "method_not_allowed",
            "the route does not take this HTTP method",
            "use one of the methods in the Allow header",
            http_status=405,
        ),
        ErrorKind(
            "conflict",
            "the request clashes with the current state: something is busy or still running, already exists, or "
            "has not finished",
            "wait until it has ended, or choose another name, then try again",
            exit_status=2,
            http_status=409,
        ),
        ErrorKind(
            "stop_latched",
            "the emergency stop is latched: nothing moves and the X-rays stay off until an operator resets it",
            "clear the cause of the stop, then an operator resets it (the console's Bench page, POST /stop/reset or "
            "orbitct reset)",
            exit_status=2,
            http_status=409,
        ),
        ErrorKind(
            "failed_quality_check",
            "the geometry asked for failed its quality check, so a volume made from it cannot be trusted",
            "read the calibration report and calibrate again, or override explicitly (--accept-failed-geometry, "
            '"accept_failed_geometry": true); the override is recorded with the volume',
            exit_status=3,
            http_status=409,
        ),
        ErrorKind(
            "request_too_large",
            "the request body is larger than the service takes",
            "send a smaller body (the service settings max_body_bytes and max_upload_bytes set the limits)",
            http_status=413,
        ),
        ErrorKind(
            "file_error",
            "a file could not be read or written (missing, no permission, damaged)",
            "check the path, its permissions and the free disk space, then run it again",
            exit_status=1,
        ),
        ErrorKind(
            "insufficient_storage",
            "the disk the data goes to is full, or too full for what was asked (a scan refused for it before anything "
            "moved exits 2)",
            "free space on that disk and try again (GET /health shows the disk state)",
            exit_status=1,
            http_status=507,
        ),
        ErrorKind(
            "bad_gateway",
            "another system the request needed (a PACS node) could not be reached or refused",
            "check that the other system is running, reachable and configured as named, then try again",
            exit_status=1,
            http_status=502,
        ),
        ErrorKind(
            "unavailable",
            "a part that is needed is not running or not answering (the bench, the service, a device)",
            "check that it is running and connected (GET /health shows what is), then try again",
            exit_status=1,
            http_status=503,
        ),
        ErrorKind(
            "action_failed",
            "the work could not be done: a scan, calibration, plan, import or reconstruction failed, or an input file "
            "cannot be used for it",
            "fix what the reason names and run it again",
            exit_status=1,
        ),
        ErrorKind(
            "interrupted",
            "the command was stopped by Ctrl-C or a signal (a scan halts every axis and switches the X-rays off); "
            "for a job (its `error`), the service stopped while it ran",
            "run it again when ready (an interrupted scan keeps its file, marked aborted)",
            exit_status=130,
        ),
        ErrorKind(
            "internal_error",
            "something orbitct did not expect went wrong",
            "try again; if it fails again, report it with the incident number (the service log has the details)",
            exit_status=1,
            http_status=500,
        ),
    )
}


def error_kind(code: str) -> ErrorKind:
    """The catalogue's entry for ``code`` (a KeyError for a code not in the catalogue: a programming error)."""
    return CATALOGUE[code]


def sentence(what: str, advice: str) -> str:
    """``what; advice``: one sentence of what happened and what to do."""
    what, advice = what.strip().rstrip(".;"), advice.strip().rstrip(".")
    return f"{what}; {advice}" if advice else what


def code_for_exception(exc: BaseException) -> str:
    """The code of a failure that ended a command, a job or a plan: a full disk, another file problem, orbitct's own
    errors (``ValueError``s that say what was wrong) and running out of memory, else unexpected."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return "insufficient_storage"
    if isinstance(exc, OSError) and not isinstance(exc, TimeoutError | ConnectionError):
        return "file_error"
    if isinstance(exc, MemoryError | ValueError):
        return "action_failed"
    return "internal_error"


def code_for_http(status: int) -> str:
    """The catalogue code of an HTTP status the service answers with (the first entry that has it)."""
    for kind in CATALOGUE.values():
        if kind.http_status == status:
            return kind.code
    return "bad_request" if status < 500 else "internal_error"
