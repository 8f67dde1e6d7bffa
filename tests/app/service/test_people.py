"""``/people``: an operator adds a person with several roles, the person signs in with the one token, and is
removed again; nobody removes their own sign-in."""

from __future__ import annotations

import pytest

from orbitct_app.service.core.auth import hash_token, read_token_file

pytestmark = pytest.mark.system


def test_an_operator_adds_and_removes_a_person_with_two_roles(shared_api) -> None:  # type: ignore[no-untyped-def]
    r = shared_api.post("/people", json={"name": "tech-1", "roles": ["operator", "analyst"]})
    assert r.status_code == 201, r.text
    made = r.json()
    token = made.pop("token")
    assert made == {"name": "tech-1", "roles": ["operator", "analyst"], "hash_prefix": hash_token(token)[:12]}
    stored = {e.name: e for e in read_token_file(shared_api.data_dir / "tokens.json")}
    assert token not in (shared_api.data_dir / "tokens.json").read_text() and stored["tech-1"].roles == made["roles"]
    listed = shared_api.get("/people", role="operator").json()
    assert {"name": "tech-1", "roles": ["operator", "analyst"], "hash_prefix": made["hash_prefix"]} in listed
    as_tech = {"Authorization": f"Bearer {token}"}
    assert shared_api.get("/people", role=None, headers=as_tech).status_code == 200
    again = shared_api.post("/people", json={"name": "tech-1", "roles": ["viewer"]})
    assert again.status_code == 409 and "exists already" in again.json()["message"]
    assert "/" not in again.json()["message"]  # the service's paths stay inside
    own = shared_api.request("DELETE", "/people/tech-1", role=None, headers=as_tech)
    assert own.status_code == 409 and "your own sign-in" in own.json()["message"]
    assert shared_api.request("DELETE", "/people/tech-1").status_code == 204
    assert shared_api.get("/scans", role=None, headers=as_tech).status_code == 401
    assert shared_api.request("DELETE", "/people/tech-1").status_code == 404


def test_people_refuses_unknown_roles_and_is_for_operators(shared_api) -> None:  # type: ignore[no-untyped-def]
    bad = shared_api.post("/people", json={"name": "x", "roles": ["admin"]})
    assert bad.status_code == 422 and bad.json()["details"][0]["field"].startswith("roles")
    refused = shared_api.get("/people", role="analyst")
    assert refused.status_code == 403 and "needs the operator role" in refused.json()["message"]
