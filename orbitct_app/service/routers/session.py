"""``/session``: the web console's sign-in (a bearer token exchanged for an HttpOnly cookie), who is signed in, sign-out."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from orbitct_app.service.core.auth import Principal
from orbitct_app.service.core.errors import ERROR_RESPONSES, ApiError
from orbitct_app.service.core.sessions import COOKIE, CSRF_HEADER
from orbitct_app.service.deps import ServiceDep, get_principal

router = APIRouter(prefix="/session", tags=["session"], responses=ERROR_RESPONSES)


class SignIn(BaseModel):
    """The bearer token to sign in with (sent in the body, never in a URL)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)
    token: str = Field(min_length=1, max_length=512, description="from `orbitct token create --role R`")


class SessionOut(BaseModel):
    """Who is signed in, their roles and what those let them do, and the CSRF token state-changing requests must
    send."""

    name: str
    role: str = Field(description="the roles as the console shows them, e.g. 'operator, analyst'")
    roles: list[str]
    permissions: list[str]
    csrf_token: str = Field(description=f"send it as the {CSRF_HEADER} header with every POST made with the cookie")


class Unauthorized(ApiError):
    """Sign-in refused: the token is unknown."""

    status = 401
    code = "unauthorized"


def _out(principal: Principal, csrf: str) -> SessionOut:
    return SessionOut(
        name=principal.name,
        role=principal.role,
        roles=list(principal.roles),
        permissions=sorted(principal.permissions),
        csrf_token=csrf,
    )


@router.post("", response_model=SessionOut, summary="Sign in (sets the session cookie)")
def sign_in(body: SignIn, service: ServiceDep, request: Request, response: Response) -> SessionOut:
    """Exchange a bearer token for an HttpOnly, SameSite=Strict session cookie; the token is not kept, only its hash."""
    opened = service.sessions.open(body.token)
    if opened is None:
        raise Unauthorized("unknown token: ask an operator for one (`orbitct token create --role R`)")
    session_id, session, principal = opened
    response.set_cookie(
        COOKIE,
        session_id,
        max_age=int(service.sessions.max_age_s),
        httponly=True,
        samesite="strict",
        secure=request.url.scheme == "https",
        path="/",
    )
    return _out(principal, session.csrf)


@router.get("", response_model=SessionOut, summary="Who is signed in")
def whoami(service: ServiceDep, request: Request, _: Annotated[Principal, Depends(get_principal)]) -> SessionOut:
    """The signed-in user of this cookie and its CSRF token."""
    signed_in = service.sessions.lookup(request.cookies.get(COOKIE, ""))
    if signed_in is None:
        raise Unauthorized("not signed in with a session cookie (a bearer token has no session)")
    session, principal = signed_in
    return _out(principal, session.csrf)


@router.post("/sign-out", status_code=204, summary="Sign out (ends the session)")
def sign_out(service: ServiceDep, request: Request, _: Annotated[Principal, Depends(get_principal)]) -> Response:
    """Forget the session and clear its cookie (needs the CSRF token like every state-changing request)."""
    service.sessions.close(request.cookies.get(COOKIE, ""))
    response = Response(status_code=204)
    response.delete_cookie(COOKIE, path="/", httponly=True, samesite="strict")
    return response
