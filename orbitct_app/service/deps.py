"""FastAPI dependencies as ``Annotated`` aliases: the service's parts and the caller's permissions."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from orbitct_app.service.core.auth import Principal
from orbitct_app.service.core.errors import Forbidden
from orbitct_app.service.core.sessions import COOKIE, CSRF_HEADER, SAFE_METHODS, csrf_ok

if TYPE_CHECKING:
    from orbitct_app.service.state import Service

_bearer = HTTPBearer(auto_error=False, description="token from `orbitct token create --role R`")


async def get_service(request: Request) -> Service:
    """The running service (settings, store, bench, jobs, events)."""
    return request.app.state.service


ServiceDep = Annotated["Service", Depends(get_service)]


async def get_principal(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> Principal:
    """Who calls: from the bearer token, else from the console's session cookie (state-changing requests made with
    the cookie need its CSRF token in ``X-CSRF-Token``); 401 if neither, 403 on a missing or wrong CSRF token."""
    challenge = {"WWW-Authenticate": "Bearer"}
    if credentials is None:
        signed_in = request.app.state.service.sessions.lookup(request.cookies.get(COOKIE, ""))
        if signed_in is None:
            raise HTTPException(401, "no bearer token and no console sign-in came with the request", headers=challenge)
        session, principal = signed_in
        if request.method not in SAFE_METHODS and not csrf_ok(session, request.headers.get(CSRF_HEADER)):
            raise Forbidden(
                f"this request came with the console's session cookie but without its {CSRF_HEADER} header",
                advice="reload the page (the console sends the header; scripts use a bearer token instead)",
            )
        return principal
    if credentials.scheme.lower() != "bearer" or not credentials.credentials:
        raise HTTPException(401, "no bearer token came with the request", headers=challenge)
    if len(credentials.credentials) > 512:
        raise HTTPException(401, "unknown token", headers=challenge)
    principal = request.app.state.service.tokens.authenticate(credentials.credentials)
    if principal is None:
        raise HTTPException(401, "unknown token", headers=challenge)
    return principal


def require(permission: str) -> Callable[..., Awaitable[Principal]]:
    """A dependency that lets through only roles granting ``permission`` (403 otherwise)."""

    async def _check(principal: Annotated[Principal, Depends(get_principal)]) -> Principal:
        if not principal.may(permission):
            raise Forbidden(principal.refusal(permission), advice=principal.refusal_advice(permission))
        return principal

    _check.__name__ = f"require_{permission}"
    return _check


Reader = Annotated[Principal, Depends(require("read"))]
Operator = Annotated[Principal, Depends(require("motion"))]
ScanOperator = Annotated[Principal, Depends(require("scan"))]
Analyst = Annotated[Principal, Depends(require("analysis"))]
Stopper = Annotated[Principal, Depends(require("stop"))]
Resetter = Annotated[Principal, Depends(require("reset"))]
PeopleManager = Annotated[Principal, Depends(require("people"))]
