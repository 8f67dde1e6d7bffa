"""``/people``: the sign-ins of the tokens file, one per person with their roles; operators add and remove them."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response
from pydantic import BaseModel, ConfigDict, Field

from orbitct_app.service.core.auth import TokenFileError, create_token, hash_token, read_token_file, revoke_token
from orbitct_app.service.core.errors import ERROR_RESPONSES, Conflict, ErrorBody, NotFound
from orbitct_app.service.core.settings import Role
from orbitct_app.service.deps import PeopleManager, ServiceDep

router = APIRouter(prefix="/people", tags=["people"], responses=ERROR_RESPONSES)
NAME = r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,63}$"


class PersonOut(BaseModel):
    """A person's sign-in: name, roles and the start of its token's hash (the token itself is never stored)."""

    name: str
    roles: list[str]
    hash_prefix: str


class PersonCreate(BaseModel):
    """A new person: a unique name and the roles they need (a technician who scans and calibrates: both)."""

    model_config = ConfigDict(extra="forbid", strict=True)
    name: str = Field(pattern=NAME, description="unique; shown in logs, on the console and in `orbitct token list`")
    roles: list[Role] = Field(min_length=1, max_length=3)


class PersonCreated(PersonOut):
    """The new sign-in with its token, shown this once: hand it to the person."""

    token: str


def _people(service: ServiceDep) -> list[PersonOut]:
    try:
        entries = read_token_file(service.settings.tokens_path)
    except TokenFileError as exc:
        raise Conflict(str(exc)) from None
    return [PersonOut(name=e.name, roles=list(e.roles), hash_prefix=e.sha256[:12]) for e in entries]


@router.get("", response_model=list[PersonOut], summary="List the people who may sign in")
def list_people(service: ServiceDep, _: PeopleManager) -> list[PersonOut]:
    """The sign-ins of the tokens file (those in the service's settings file are managed there)."""
    return _people(service)


@router.post(
    "",
    response_model=PersonCreated,
    status_code=201,
    summary="Add a person",
    responses={409: {"model": ErrorBody, "description": "that name is taken"}},
)
def add_person(body: PersonCreate, service: ServiceDep, who: PeopleManager) -> PersonCreated:
    """Create a sign-in with the given roles; the token is in this answer only."""
    try:
        token = create_token(service.settings.tokens_path, body.roles, body.name)
    except TokenFileError as exc:
        raise Conflict(str(exc).replace(str(service.settings.tokens_path), "the tokens file")) from None
    roles = list(dict.fromkeys(body.roles))  # as create_token stored them
    return PersonCreated(name=body.name, roles=roles, hash_prefix=hash_token(token)[:12], token=token)


@router.delete(
    "/{name}",
    status_code=204,
    response_class=Response,
    summary="Remove a person",
    responses={409: {"model": ErrorBody, "description": "it is the caller's own sign-in"}},
)
def remove_person(name: Annotated[str, Path(pattern=NAME)], service: ServiceDep, who: PeopleManager) -> Response:
    """Remove a sign-in: its token is refused from the next request on. Nobody removes their own."""
    if name == who.name:
        raise Conflict("you cannot remove your own sign-in", advice="ask another operator to remove it")
    if not any(p.name == name for p in _people(service)):
        raise NotFound(f"nobody named {name!r} may sign in here")
    revoke_token(service.settings.tokens_path, name)
    return Response(status_code=204)


__all__ = ["router"]
