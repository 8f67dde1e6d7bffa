"""``/session``: a token exchanged for an HttpOnly cookie; cookie requests that change state need the CSRF token;
revoking the token or signing out ends the session; a stop from a session goes through the guard like any other."""

from __future__ import annotations

import pytest

from orbitct_app.service.core.auth import revoke_token
from orbitct_app.service.core.sessions import COOKIE, CSRF_HEADER
from tests.helpers.service import SMALL_SAWTOOTH, ended, wait_for


def _sign_in(api, role: str) -> str:  # type: ignore[no-untyped-def]
    api.client.cookies.clear()
    r = api.client.post("/session", json={"token": api.tokens[role]})
    assert r.status_code == 200, r.text
    cookie = r.headers["set-cookie"]
    assert f"{COOKIE}=" in cookie and "HttpOnly" in cookie and "SameSite=strict" in cookie and "Path=/" in cookie
    assert api.tokens[role] not in cookie
    body = r.json()
    assert body["role"] == role and body["name"] == f"test-{role}" and len(body["csrf_token"]) >= 32
    return str(body["csrf_token"])


def test_a_session_reads_with_the_cookie_and_changes_state_only_with_the_csrf_token(shared_api) -> None:  # type: ignore[no-untyped-def]
    api = shared_api
    csrf = _sign_in(api, "operator")
    assert api.client.get("/scans").status_code == 200  # reads need only the cookie
    assert api.client.get("/session").json()["csrf_token"] == csrf
    refused = api.client.post("/stop/reset", json={"note": "x"})  # a forged cross-site POST carries no CSRF header
    assert refused.status_code == 403 and CSRF_HEADER in refused.json()["message"]
    wrong = api.client.post("/stop/reset", json={"note": "x"}, headers={CSRF_HEADER: "not-it"})
    assert wrong.status_code == 403
    allowed = api.client.post("/stop/reset", json={"note": "x"}, headers={CSRF_HEADER: csrf})
    assert allowed.status_code == 409 and "not latched" in allowed.json()["message"]
    # roles hold as with the bearer token
    _sign_in(api, "viewer")
    forbidden = api.client.post(
        "/scans",
        json={**SMALL_SAWTOOTH, "frames": 4},
        headers={CSRF_HEADER: api.client.get("/session").json()["csrf_token"]},
    )
    assert forbidden.status_code == 403 and "viewer" in forbidden.json()["message"]
    api.client.cookies.clear()


def test_unknown_tokens_sign_out_and_revocation_end_access(api, tmp_path) -> None:  # type: ignore[no-untyped-def]
    r = api.client.post("/session", json={"token": "oct_not_a_token"})
    assert r.status_code == 401 and "unknown token" in r.json()["message"] and "set-cookie" not in r.headers
    assert api.client.post("/session", json={}).status_code == 422

    csrf = _sign_in(api, "analyst")
    assert api.client.post("/session/sign-out").status_code == 403  # sign-out needs the CSRF token too
    assert api.client.post("/session/sign-out", headers={CSRF_HEADER: csrf}).status_code == 204
    assert api.client.get("/scans").status_code == 401

    _sign_in(api, "viewer")
    assert api.client.get("/scans").status_code == 200
    revoke_token(api.data_dir / "tokens.json", "test-viewer")
    r = api.client.get("/scans")
    assert r.status_code == 401 and "sign in" in r.json()["message"]
    api.client.cookies.clear()


@pytest.mark.system
def test_a_stop_from_a_session_goes_through_the_guard_for_the_signed_in_user(api) -> None:  # type: ignore[no-untyped-def]
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 300})
    scan_id = r.json()["id"]
    wait_for(api, f"/scans/{scan_id}", lambda b: b["progress"].get("done", 0) >= 5)
    csrf = _sign_in(api, "viewer")
    stop = api.client.post("/stop", json={"reason": "console"}, headers={CSRF_HEADER: csrf})
    assert stop.status_code == 202, stop.text
    body = stop.json()
    assert body["via"] == "guard" and body["halted"] and body["latched"] and body["by"] == "test-viewer (viewer)"
    assert body["scan_aborted"] == scan_id
    assert wait_for(api, f"/scans/{scan_id}", ended, 30)["state"] == "aborted"
    api.client.cookies.clear()
    # the guard's forwarding secret is the web server's alone: a made-up "on behalf" header is refused
    import httpx

    from orbitct_app.service.core.auth import ON_BEHALF_HEADER

    guard = api.service.guard.url
    forged = httpx.post(f"{guard}/stop", headers={"Authorization": "Bearer guess", ON_BEHALF_HEADER: "eve|operator"})
    assert forged.status_code == 401
