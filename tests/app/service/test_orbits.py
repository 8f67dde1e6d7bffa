"""``/orbits``: kinds with schemas, validation, PNG preview."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.system


def test_kinds_with_parameter_schemas(shared_api) -> None:  # type: ignore[no-untyped-def]
    kinds = {k["kind"]: k for k in shared_api.get("/orbits").json()}
    assert {"circular", "sawtooth", "dcarc"} <= set(kinds)
    props = kinds["sawtooth"]["parameters"]["properties"]
    assert props["amplitude_deg"]["maximum"] == 60
    assert "path" not in kinds["waypoints"]["parameters"]["properties"]
    assert shared_api.get("/orbits/sawtooth").json()["kind"] == "sawtooth"


def test_validate(shared_api) -> None:  # type: ignore[no-untyped-def]
    r = shared_api.post(
        "/orbits/validate", role="viewer", json={"kind": "sawtooth", "params": {"n_frames": 100, "amplitude_deg": 10}}
    )
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["n_frames"] == 100 and body["tilt_deg"][1] <= 10.0 + 1e-9
    r = shared_api.post(
        "/orbits/validate", role="viewer", json={"kind": "dcarc", "params": {"arc_start_deg": 5, "arc_end_deg": 5}}
    )
    assert r.status_code == 422 and "differ" in r.json()["message"]


def test_preview_png(shared_api) -> None:  # type: ignore[no-untyped-def]
    r = shared_api.post("/orbits/preview", role="viewer", json={"kind": "circular", "params": {"n_frames": 50}})
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert r.content[:8] == b"\x89PNG\r\n\x1a\n"
