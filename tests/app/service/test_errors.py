"""Errors are JSON with a clear message: 404 unknown ids, 422 field and reason, 413 big bodies, no traversal."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.system


def _is_error(r, status: int) -> dict:  # type: ignore[no-untyped-def]
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == {"error", "message", "advice", "details"} and body["message"].endswith(body["advice"])
    return body


@pytest.mark.parametrize(
    "path",
    [
        "/scans/0123456789abcdef",
        "/jobs/0123456789abcdef",
        "/calibrations/x",
        "/reconstructions/x",
        "/scans/x/file",
        "/jobs/x/log",
        "/nowhere",
        "/orbits/spiral",
    ],
)
def test_unknown_ids_are_404(shared_api, path: str) -> None:  # type: ignore[no-untyped-def]
    assert _is_error(shared_api.get(path), 404)["error"] == "not_found"


def test_invalid_parameters_name_field_and_reason(shared_api) -> None:  # type: ignore[no-untyped-def]
    body = _is_error(shared_api.post("/scans", json={"orbit": "sawtooth", "params": {"amplitude_deg": 500}}), 422)
    assert body["details"][0]["field"] == "params.amplitude_deg" and "60" in body["details"][0]["reason"]
    body = _is_error(shared_api.post("/scans", json={"orbit": "spiral"}), 422)
    assert body["details"][0]["field"] == "orbit"
    body = _is_error(shared_api.post("/reconstructions", role="analyst", json={"scan_id": "x", "iterations": 0}), 422)
    assert body["details"][0]["field"] == "iterations"
    body = _is_error(
        shared_api.post("/reconstructions", role="analyst", json={"scan_id": "x", "shape": [2048, 2048, 512]}), 422
    )
    assert "voxels" in body["message"]
    body = _is_error(shared_api.post("/reconstructions", role="analyst", json={"scan_id": "x", "stream": "disk"}), 422)
    assert body["details"][0]["field"] == "stream" and "file" in body["details"][0]["reason"]
    body = _is_error(shared_api.post("/scans", json={"orbit": "circular", "frames": 10**6}), 422)
    assert body["details"][0]["field"] == "frames"
    body = _is_error(shared_api.post("/scans", json={"orbit": "waypoints", "params": {"path": "/etc/passwd"}}), 422)
    assert body["details"][0]["field"] == "params.path"
    body = _is_error(
        shared_api.post(
            "/calibrations",
            role="analyst",
            content=b'{"scan_id": "x",, }',
            headers={"Content-Type": "application/json"},
        ),
        422,
    )
    assert body["details"][0]["field"] == "body" and "not valid JSON at character" in body["details"][0]["reason"]
    _is_error(shared_api.get("/jobs", params={"limit": -1}), 422)


def test_request_size_is_bounded(shared_api) -> None:  # type: ignore[no-untyped-def]
    big = {"orbit": "circular", "params": {"x": "a" * 200_000}}
    assert _is_error(shared_api.post("/scans", json=big), 413)["error"] == "request_too_large"


def test_downloads_stay_in_the_data_dir(shared_api) -> None:  # type: ignore[no-untyped-def]
    (shared_api.data_dir / "jobs" / "j1").mkdir(parents=True)
    for name in ("..%2F..%2Ftokens.json", "%2E%2E", "..", ".hidden", "a%00b"):
        r = shared_api.get(f"/calibrations/j1/files/{name}")
        assert r.status_code == 404, (name, r.status_code)
    from orbitct_app.service.core.errors import NotFound
    from orbitct_app.service.core.files import confined

    (shared_api.data_dir / "jobs" / "j1" / "link").symlink_to(shared_api.data_dir / "tokens.json")
    with pytest.raises(NotFound):
        confined(shared_api.data_dir / "jobs" / "j1", "link")
    with pytest.raises(NotFound):
        confined(shared_api.data_dir / "jobs", "..", "tokens.json")


def test_wrong_method_is_json(shared_api) -> None:  # type: ignore[no-untyped-def]
    r = shared_api.request("DELETE", "/scans")
    assert _is_error(r, 405)["error"] == "method_not_allowed"
    assert r.headers["allow"] == "GET, POST" and r.json()["advice"] == "use GET or POST"


def test_the_openapi_document_is_valid_openapi_3_1(shared_api) -> None:  # type: ignore[no-untyped-def]
    from openapi_spec_validator import validate

    spec = shared_api.client.app.openapi()
    assert spec["openapi"].startswith("3.1")
    validate(spec)
    start = spec["paths"]["/scans"]["post"]["responses"]
    assert {"202", "401", "403", "409", "422", "507"} <= set(start)  # every status the route answers with
    recon = spec["paths"]["/reconstructions"]["post"]["responses"]
    assert {"202", "409", "422"} <= set(recon)


def test_an_unexpected_failure_in_the_bench_process_is_an_internal_error_with_an_incident(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A bench command that fails in a way nobody expected answers 500 internal_error (it was 503 unavailable, as
    if the devices were not connected), with an incident number whose traceback is in the bench process's log."""
    import asyncio
    import multiprocessing as mp
    from pathlib import Path

    from orbitct_app.service.rig.client import ERROR_KINDS
    from orbitct_app.service.rig.process import RigServer

    ours, theirs = mp.Pipe()
    server = RigServer(Path("bench.yaml"), True, theirs)

    async def cmd_boom() -> None:
        raise RuntimeError("a bug")

    server.cmd_boom = cmd_boom  # type: ignore[attr-defined]
    with caplog.at_level("ERROR", logger="orbitct.service.rig.process"):
        asyncio.run(server._run_command(7, "boom", {}))
    assert ours.poll(5)
    kind, req_id, ok, (err_kind, text) = ours.recv()
    assert (kind, req_id, ok, err_kind) == ("reply", 7, False, "error")
    incident = text.split("(incident ")[1].split(")")[0]
    assert text.startswith("an internal error in the bench process stopped the command (incident ")
    assert "RuntimeError" not in text and incident in caplog.text and "a bug" in caplog.text
    error = ERROR_KINDS[err_kind](text)
    assert (error.status, error.code) == (500, "internal_error")
