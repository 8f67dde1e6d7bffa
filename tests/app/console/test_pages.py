"""The console's pages as the server renders them: sign-in first, controls by role, no token in the page, strict
content security policy, the API docs from orbitct's own files."""

from __future__ import annotations

import re

import pytest

from orbitct_app.service.core.sessions import CSRF_HEADER
from tests.helpers.service import SMALL_SAWTOOTH, ended, wait_for

PAGES = [
    "/console/bench",
    "/console/scans/new",
    "/console/scans",
    "/console/jobs",
    "/console/plans",
    "/console/scans/abc",
    "/console/calibrations/abc",
    "/console/reconstructions/abc",
]


def _sign_in(api, role: str) -> str:  # type: ignore[no-untyped-def]
    api.client.cookies.clear()
    r = api.client.post("/session", json={"token": api.tokens[role]})
    assert r.status_code == 200, r.text
    return str(r.json()["csrf_token"])


def test_pages_need_a_session_and_the_home_is_the_bench(shared_api) -> None:  # type: ignore[no-untyped-def]
    api = shared_api
    api.client.cookies.clear()
    home = api.client.get("/", follow_redirects=False)
    assert home.status_code == 303 and home.headers["location"] == "/console/bench"
    for path in PAGES:
        r = api.client.get(path, follow_redirects=False)
        assert r.status_code == 303 and r.headers["location"].startswith("/sign-in?next=/console/"), path
    sign_in = api.client.get("/sign-in?next=https://evil.example/")
    assert sign_in.status_code == 200 and 'data-next="/console/bench"' in sign_in.text  # no open redirect
    assert 'type="password"' in sign_in.text


@pytest.mark.parametrize("role", ["operator", "analyst", "viewer"])
def test_every_page_renders_for_every_role_without_the_token_and_with_a_strict_policy(shared_api, role) -> None:  # type: ignore[no-untyped-def]
    api = shared_api
    csrf = _sign_in(api, role)
    for path in PAGES:
        r = api.client.get(path)
        assert r.status_code == 200, (path, r.text[:300])
        assert api.tokens[role] not in r.text and api.tokens[role] not in str(r.headers)
        assert f'content="{csrf}"' in r.text  # the CSRF token, for the page's script
        policy = r.headers["content-security-policy"]
        assert (
            "default-src 'self'" in policy
            and "script-src 'self'" in policy
            and "unsafe-inline" not in policy.split("script-src")[1].split(";")[0]
        )
        assert 'id="estop"' in r.text, "the emergency stop is on every page"
        assert not re.search(r'(src|href)="(https?:)?//', r.text), "nothing from outside orbitct"
    api.client.cookies.clear()


def test_pages_render_only_the_controls_of_the_role(shared_api) -> None:  # type: ignore[no-untyped-def]
    api = shared_api
    expect = {  # page -> marker of a control -> roles that see it
        "/console/bench": {
            'class="reference"': {"operator"},
            'class="move"': {"operator"},
            'id="reset-stop"': {"operator"},
        },
        "/console/scans/new": {'id="start"': {"operator"}},
        "/console/scans/abc": {
            'id="abort"': {"operator"},
            'id="calibrate-form"': {"analyst"},
            'id="reconstruct-form"': {"analyst"},
        },
    }
    for role in ("operator", "analyst", "viewer"):
        _sign_in(api, role)
        for path, markers in expect.items():
            html = api.client.get(path).text
            for marker, roles in markers.items():
                assert (marker in html) == (role in roles), (role, path, marker)
    api.client.cookies.clear()


def test_a_new_scan_may_stop_on_every_live_warning_but_the_good_news(shared_api) -> None:  # type: ignore[no-untyped-def]
    from orbitct.livewarnings import ABORT_KINDS

    api = shared_api
    _sign_in(api, "operator")
    html = api.client.get("/console/scans/new").text
    offered = re.findall(r'<div id="abort-on">(.*?)</div>', html, re.S)[0]
    assert re.findall(r'value="([a-z_]+)"', offered) == list(ABORT_KINDS)
    assert "the object moved on the table" in offered and "bb_found" not in offered
    api.client.cookies.clear()


def test_the_api_docs_use_orbitcts_own_copies_of_swagger_ui_and_redoc(shared_api) -> None:  # type: ignore[no-untyped-def]
    api = shared_api
    for path in ("/docs", "/redoc"):
        page = api.client.get(path)
        assert page.status_code == 200
        assets = re.findall(r'(?:src|href)="([^"]+)"', page.text)
        assert assets and all(a.startswith("/") for a in assets), assets
        for asset in assets:
            assert api.client.get(asset).status_code == 200, asset
        assert "fonts.googleapis" not in page.text and "cdn." not in page.text


@pytest.mark.system
def test_preflight_names_the_first_infeasible_frame_and_the_live_frame_follows_the_scan(api) -> None:  # type: ignore[no-untyped-def]
    ok = api.post("/scans/preflight", role="viewer", json={**SMALL_SAWTOOTH, "frames": 20})
    assert ok.status_code == 200 and ok.json()["frames"] == 20 and "within the limits" in ok.json()["message"]
    fast = api.post(
        "/scans/preflight", json={**SMALL_SAWTOOTH, "frames": 500, "frame_rate_hz": 1000.0, "mode": "continuous"}
    )
    assert fast.status_code == 422 and "at 1000 frames/s" in fast.json()["message"], fast.text  # too fast for the stage
    assert api.post("/scans/preflight", json={**SMALL_SAWTOOTH, "frame_rate_hz": 0}).status_code == 422
    too_far = api.post("/scans/preflight", json={"orbit": "sawtooth", "params": {"amplitude_deg": 40.0}, "frames": 50})
    assert too_far.status_code == 422 and "frame" in too_far.json()["message"], too_far.text
    assert not list(api.data_dir.rglob("*.h5")), "a pre-flight writes nothing"

    scan_id = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 200}).json()["id"]
    wait_for(api, f"/scans/{scan_id}", lambda b: b["progress"].get("done", 0) >= 6)
    frame = api.get(f"/scans/{scan_id}/frames/latest")
    assert frame.status_code == 200, frame.text
    body = frame.json()
    assert (
        body["width"] == body["height"] == 192
        and body["scale"] == 1.0
        and body["kind"] in ("projection", "flat", "dark")
    )
    import base64

    assert len(base64.b64decode(body["pixels"])) == 192 * 192
    api.post(f"/scans/{scan_id}/abort", json={"reason": "test"})
    wait_for(api, f"/scans/{scan_id}", ended, 30)
    gone = api.get(f"/scans/{scan_id}/frames/latest")
    assert gone.status_code == 409 and "not running" in gone.json()["message"]


def test_a_viewer_session_is_refused_what_its_page_does_not_offer(shared_api) -> None:  # type: ignore[no-untyped-def]
    api = shared_api
    csrf = _sign_in(api, "viewer")
    for method, path, body in (
        ("POST", "/scans", {**SMALL_SAWTOOTH, "frames": 4}),
        ("POST", "/devices/hexapod/reference", None),
        ("POST", "/calibrations", {"scan_id": "abc"}),
    ):
        r = api.client.request(method, path, json=body, headers={CSRF_HEADER: csrf})
        assert r.status_code == 403 and "viewer" in r.json()["message"], (path, r.text)
    api.client.cookies.clear()
