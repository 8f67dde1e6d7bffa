"""JSON errors for the API: a stable ``error`` code from the catalogue (:mod:`orbitct_app.error_codes`), one sentence
``message`` of what happened and what to do, the ``advice`` part apart; never internals."""

from __future__ import annotations

import errno
import logging
import re
import sqlite3
import uuid
from collections.abc import Mapping, Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from orbitct_app.error_codes import code_for_http, error_kind, sentence
from orbitct_app.service.core.db import StoreUnavailable

log = logging.getLogger("orbitct.service")
FIELD_ADVICE = "correct the field named and send it again (GET /docs lists each route's fields)"


class FieldProblem(BaseModel):
    """One invalid field: where it is and why it was refused."""

    field: str
    reason: str


class ErrorBody(BaseModel):
    """Every error response of the API."""

    error: str  # the stable code (the documentation's error catalogue lists them)
    message: str  # what happened; what to do
    advice: str = ""  # what to do (the end of the message)
    details: list[FieldProblem] = []


class ApiError(Exception):
    """An error the API reports as is: HTTP status, code, what happened and what to do (``advice``; the catalogue's
    for the code when not given)."""

    status = 400
    code = "bad_request"

    def __init__(self, message: str, *, advice: str | None = None, details: list[FieldProblem] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.advice = error_kind(self.code).advice if advice is None else advice
        self.details = details or []


class Forbidden(ApiError):
    """The person signed in may not do this (a role is missing, or the console's CSRF header)."""

    status, code = 403, "forbidden"


class NotFound(ApiError):
    """An unknown id or resource."""

    status, code = 404, "not_found"


class Conflict(ApiError):
    """The request clashes with the current state (busy bench, aborted scan, ...)."""

    status, code = 409, "conflict"


class StopLatched(ApiError):
    """The emergency stop is latched: nothing may move or expose until an operator resets it."""

    status, code = 409, "stop_latched"


class FailedCheck(ApiError):
    """The result asked for would be made from one that failed its quality check (a calibrated geometry); the
    request must say explicitly that it is to be used anyway."""

    status, code = 409, "failed_quality_check"


class Invalid(ApiError):
    """Parameters that are well-formed but not acceptable."""

    status, code = 422, "invalid_parameters"


class InsufficientStorage(ApiError):
    """The data directory's disk has too little free space for what was asked."""

    status, code = 507, "insufficient_storage"


class Upstream(ApiError):
    """Another system the request needed (a PACS node) could not be reached or refused."""

    status, code = 502, "bad_gateway"


class Internal(ApiError):
    """Something orbitct did not expect went wrong (the log has the details under the incident number)."""

    status, code = 500, "internal_error"


class Unavailable(ApiError):
    """A part of the service that is not ready (devices not connected)."""

    status, code = 503, "unavailable"


ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    400: {
        "model": ErrorBody,
        "description": "the request body cannot be read (not UTF-8 JSON, or sent with a content "
        "type the route does not take)",
    },
    401: {"model": ErrorBody, "description": "missing or unknown bearer token"},
    403: {"model": ErrorBody, "description": "the token's role may not do this"},
    404: {"model": ErrorBody, "description": "unknown id or file"},
    413: {
        "model": ErrorBody,
        "description": "the request body is larger than the service's max_body_bytes (max_upload_bytes for uploads)",
    },
    422: {"model": ErrorBody, "description": "invalid parameters: field and reason in `details`"},
}
NOT_SUCCEEDED: dict[int | str, dict[str, Any]] = {
    409: {
        "model": ErrorBody,
        "description": "the job has not succeeded (queued, running, failed or cancelled); its "
        "results exist once it has",
    }
}
BENCH_UNAVAILABLE: dict[int | str, dict[str, Any]] = {
    503: {"model": ErrorBody, "description": "the bench process is not connected or did not answer in time"}
}
DISK_FULL: dict[int | str, dict[str, Any]] = {
    507: {"model": ErrorBody, "description": "the data directory's disk is full (GET /health shows the disk state)"}
}


def _field_name(loc: tuple[Any, ...] | list[Any]) -> str:
    parts = [str(p) for p in loc if p not in ("body",)]
    return ".".join(parts) or "body"


def _problem(e: Mapping[str, Any]) -> FieldProblem:
    if e.get("type") == "json_invalid":  # the location is a character position, not a field
        loc = list(e.get("loc", ()))
        at = f" at character {loc[-1]}" if loc and isinstance(loc[-1], int) else ""
        why = (e.get("ctx") or {}).get("error", "")
        return FieldProblem(field="body", reason=f"not valid JSON{at}" + (f" ({why})" if why else ""))
    return FieldProblem(field=_field_name(e.get("loc", ())), reason=str(e.get("msg", "invalid"))[:300])


def validation_details(errors: Sequence[Mapping[str, Any]]) -> list[FieldProblem]:
    """Field and reason for each pydantic error (no input echo beyond the message)."""
    return [_problem(e) for e in errors]


def _json(
    status: int,
    code: str,
    message: str,
    details: list[FieldProblem] | None = None,
    headers: dict[str, str] | None = None,
    advice: str | None = None,
) -> JSONResponse:
    advice = error_kind(code).advice if advice is None else advice
    body = ErrorBody(error=code, message=sentence(message, advice), advice=advice, details=details or [])
    return JSONResponse(body.model_dump(), status_code=status, headers=headers)


def disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` says the disk is full (``ENOSPC``, SQLite's "database or disk is full")."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    if isinstance(exc, StoreUnavailable):
        return exc.disk_full
    return isinstance(exc, sqlite3.OperationalError) and "disk is full" in str(exc)


def _allowed_methods(app: FastAPI, request: Request) -> list[str]:
    """The methods the OpenAPI document lists for this request's path: the most specific path template that matches
    it (``/orbits/preview``, not ``/orbits/{kind}`` as well), so that ``Allow`` says what the contract says."""
    path = request.url.path
    matching = [
        t for t in app.openapi().get("paths", {}) if re.fullmatch(re.sub(r"\\\{[^}]+\\\}", "[^/]+", re.escape(t)), path)
    ]
    if not matching:
        return []
    template = min(matching, key=lambda t: (t.count("{"), -len(t)))
    operations = app.openapi()["paths"][template]
    return [m.upper() for m in ("get", "head", "post", "put", "patch", "delete") if m in operations]


def install_error_handlers(app: FastAPI) -> None:
    """Register handlers that turn every failure into an :class:`ErrorBody`."""

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return _json(exc.status, exc.code, exc.message, exc.details, advice=exc.advice)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        details = validation_details(list(exc.errors()))
        msg = "; ".join(f"{d.field}: {d.reason}" for d in details[:5]) or "invalid request"
        return _json(422, "invalid_parameters", msg, details, advice=FIELD_ADVICE)

    @app.exception_handler(ValidationError)
    async def _model_validation(request: Request, exc: ValidationError) -> JSONResponse:
        details = validation_details(list(exc.errors()))
        msg = "; ".join(f"{d.field}: {d.reason}" for d in details[:5]) or "invalid parameters"
        return _json(422, "invalid_parameters", msg, details, advice=FIELD_ADVICE)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = code_for_http(exc.status_code)
        message = exc.detail if isinstance(exc.detail, str) else code.replace("_", " ")
        advice = None
        if exc.status_code == 400 and message == "There was an error parsing the body":  # FastAPI's own words
            message = "the request body cannot be read"
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:  # every method of the path, not only those of the first route that matched it
            allowed = _allowed_methods(app, request)
            headers["Allow"] = ", ".join(allowed)
            message = f"{request.method} is not allowed on {request.url.path}"
            advice = f"use {' or '.join(allowed)}" if allowed else None
        return _json(exc.status_code, code, message, headers=headers or None, advice=advice)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        if isinstance(exc, StoreUnavailable) and not exc.disk_full:  # read-only or locked: the cause, in words
            log.error("%s %s: %s", request.method, request.url.path, exc)
            return _json(503, "unavailable", str(exc))
        if disk_full(exc):
            log.error("disk full on %s %s: %s", request.method, request.url.path, exc)
            return _json(507, "insufficient_storage", "the data directory's disk is full")
        incident = uuid.uuid4().hex[:12]
        log.exception("internal error %s on %s %s", incident, request.method, request.url.path)
        return _json(500, "internal_error", f"an internal error stopped the request (incident {incident})")


class ContentLengthLimit:
    """ASGI middleware: a JSON 413 for any request body over ``max_bytes`` (declared or streamed), or over the limit
    ``larger`` gives the paths that start with one of its prefixes (uploads)."""

    def __init__(self, app: Any, max_bytes: int, larger: dict[str, int] | None = None) -> None:
        self.app, self.max_bytes, self.larger = app, max_bytes, dict(larger or {})

    async def _refuse(self, scope: Any, receive: Any, send: Any, limit: int) -> None:
        response = _json(413, "request_too_large", f"the request body is larger than {limit} bytes")
        await response(scope, receive, send)

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "")
        limit = next((n for prefix, n in self.larger.items() if path.startswith(prefix)), self.max_bytes)
        length = dict(scope.get("headers", ())).get(b"content-length")
        if length is not None:
            try:
                too_big = int(length) > limit
            except ValueError:
                too_big = True
            if too_big:
                await self._refuse(scope, receive, send, limit)
                return
            await self.app(scope, receive, send)
            return
        if scope.get("method") in ("GET", "HEAD", "OPTIONS", "DELETE"):
            await self.app(scope, receive, send)
            return
        # no declared length (chunked): read the body up to the limit first, then replay it
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                break
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            if size > limit:
                await self._refuse(scope, receive, send, limit)
                return
            if not message.get("more_body", False):
                break
        body, sent = b"".join(chunks), False

        async def replay() -> Any:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)
