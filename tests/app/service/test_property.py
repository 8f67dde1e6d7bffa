"""Property-based: random requests built from the app's own OpenAPI schema, headers such as ``Last-Event-ID``
included, never get a 5xx, and every status they get is one the schema documents for that route."""

from __future__ import annotations

import re
from typing import Any
from urllib.parse import quote, unquote

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers.service import SMALL_SAWTOOTH, ended, wait_for

pytestmark = pytest.mark.system

JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**12), 10**12)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=12), children, max_size=4),
    max_leaves=12,
)
IDS = st.sampled_from(
    [
        "",
        "x",
        "..",
        "%2e%2e",
        "0123456789abcdef",
        "a" * 70,
        "hexapod",
        "xray",
        "axial",
        "sawtooth",
        "table1.csv",
        "../tokens.json",
        "%00",
        "ünï",
        "-1",
        "1e9",
    ]
) | st.text(max_size=30)
# side effects the fuzzer must not cause: real scans and moves are tested elsewhere
SKIP = {("post", "/stop"), ("post", "/devices/{name}/reference")}
ENDLESS = {"/stop/events"}  # the stop stream stays open for as long as the client listens
HEADER_VALUES = st.sampled_from(["", "0", "3", "-1", "1e3", "²", "٣", "9" * 40, "nan", " 7 "]) | st.text(max_size=12)


def _operations(app: Any) -> list[tuple[str, str, dict[str, Any]]]:
    ops = []
    for path, item in app.openapi()["paths"].items():
        for method, op in item.items():
            if (method, path) not in SKIP and path not in ENDLESS:
                ops.append((method, path, op))
    return ops


def _value_for(schema: dict[str, Any], draw: Any) -> Any:
    if "enum" in schema:
        return draw(st.sampled_from(schema["enum"]) | JSON)
    kinds = {
        "integer": st.integers(-(10**6), 10**6),
        "number": st.floats(-1e6, 1e6),
        "boolean": st.booleans(),
        "string": st.text(max_size=20),
    }
    return draw(kinds.get(schema.get("type", ""), JSON) | JSON)


@st.composite
def requests(
    draw: Any, ops: list[tuple[str, str, dict[str, Any]]], schemas: dict[str, Any], known: list[str]
) -> tuple[str, str, str, dict[str, Any]]:
    method, path, op = draw(st.sampled_from(ops))
    ids = st.sampled_from(known) | IDS  # ids that exist reach the routes' deeper answers (409, 400, files)
    url = re.sub(r"\{[^}]+\}", lambda m: quote(draw(ids), safe="%.") or "x", path)
    params = {}
    for p in op.get("parameters", []):
        if p["in"] == "query" and draw(st.booleans()):
            params[p["name"]] = str(_value_for(p.get("schema", {}), draw))
    kwargs: dict[str, Any] = {"params": params}
    if draw(st.booleans()):
        kwargs["headers"] = {"Last-Event-ID": draw(HEADER_VALUES).encode("utf-8")}  # raw bytes, as on the wire
    if "requestBody" in op and "application/json" not in op["requestBody"]["content"]:  # an upload: raw bytes
        kwargs["content"] = draw(st.binary(max_size=64))
    elif "requestBody" in op:
        ref = op["requestBody"]["content"]["application/json"]["schema"].get("$ref", "")
        model = schemas.get(ref.rsplit("/", 1)[-1], {})
        examples = model.get("examples", [])
        if examples and draw(st.booleans()):
            body = dict(draw(st.sampled_from(examples)))
            for key in draw(st.lists(st.sampled_from(sorted(model.get("properties", {"x": {}}))), max_size=3)):
                body[key] = _value_for(model.get("properties", {}).get(key, {}), draw)
            if body.get("frames") is not None and isinstance(body["frames"], int):
                body["frames"] = min(abs(body["frames"]), 6)  # a valid scan stays tiny
        else:
            body = draw(JSON)
        kwargs["json"] = body
    return method.upper(), url, path, kwargs


def _existing_ids(api: Any) -> list[str]:
    """A finished scan, a finished reconstruction and a finished calibration of it, and their files' names."""
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 6})
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    assert wait_for(api, f"/scans/{scan_id}", ended)["state"] == "complete"
    jobs = [
        api.post(
            "/reconstructions", role="analyst", json={"scan_id": scan_id, "geometry": "nominal", "shape": [8, 8, 8]}
        ),
        api.post("/calibrations", role="analyst", json={"scan_id": scan_id}),
    ]  # six frames: this one fails, which is fine
    known = [scan_id, "x", "y", "z", "table1.csv", "volume.nii.gz"]
    for r in jobs:
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        wait_for(api, f"/jobs/{job_id}", lambda b: b["state"] in ("succeeded", "failed", "cancelled"))
        known.append(job_id)
        files = api.get(f"/jobs/{job_id}").json().get("files") or []
        known += [f["name"] if isinstance(f, dict) else str(f) for f in files]
    return known


def test_no_5xx_for_any_request(shared_api) -> None:  # type: ignore[no-untyped-def]
    app = shared_api.client.app
    ops = _operations(app)
    schemas = app.openapi()["components"]["schemas"]

    documented = {(m.upper(), p): set(op.get("responses", {})) for m, p, op in ops}
    known = _existing_ids(shared_api)

    @settings(max_examples=250, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
    @given(req=requests(ops, schemas, known), role=st.sampled_from(["operator", "analyst", "viewer", "dev"]))
    def check(req: tuple[str, str, str, dict[str, Any]], role: str) -> None:
        method, url, path, kwargs = req
        r = shared_api.request(method, url, role=role, **kwargs)
        assert r.status_code < 500, (method, url, kwargs, r.status_code, r.text[:500])
        if r.status_code >= 400:
            body = r.json()
            assert body["error"] and body["message"]
        # a method the path lacks has no operation to document it; '..' in an id leads to another route
        if r.status_code != 405 and not {".", ".."} & {unquote(part) for part in url.split("/")}:
            assert str(r.status_code) in documented[(method, path)], (method, path, r.status_code, r.text[:300])

    check()
