"""Emergency stop during a scan: every axis halted, X-rays off, scan aborted; busy bench answers 409."""

from __future__ import annotations

import time

import pytest

from orbitct.scanfile import ScanFile
from tests.helpers.service import (
    SMALL_CARM_SAWTOOTH,
    SMALL_SAWTOOTH,
    ended,
    small_carm_config,
    wait_for,
)

pytestmark = pytest.mark.system

def _start(api, frames: int = 300) -> str:  # type: ignore[no-untyped-def]
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": frames})
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    wait_for(api, f"/scans/{scan_id}", lambda b: b["progress"].get("done", 0) >= 8)
    return scan_id

def test_emergency_stop_halts_axes_xrays_and_aborts_the_scan(api) -> None:  # type: ignore[no-untyped-def]
    scan_id = _start(api)
    t0 = time.monotonic()
    r = api.post("/stop", role="viewer")  # anyone who can see the bench may stop it
    elapsed = time.monotonic() - t0
    assert r.status_code == 202, r.text
    body = r.json()
    assert body["halted"] is True and body["scan_aborted"] == scan_id
    assert elapsed < 2.0
    scan = wait_for(api, f"/scans/{scan_id}", ended, 30)
    assert scan["state"] == "aborted" and "emergency stop" in scan["reason"]
    xray = api.get("/devices/xray").json()["state"]
    assert xray["hv_on"] is False and xray["exposing"] is False
    for name in ("hexapod", "rotation_stage"):
        state = api.get(f"/devices/{name}").json()["state"]
        assert state["moving"] is False, (name, state)
    with ScanFile(api.data_dir / "scans" / f"{scan_id}.h5") as sf:
        assert sf.status == "aborted" and "emergency stop" in sf.status_reason
        assert sf.n_frames >= 8
    # the bench is usable again
    assert api.post("/devices/rotation_stage/move", json={"targets": {"R": 1.0}}).status_code == 200

def test_stop_when_idle_is_accepted(api) -> None:  # type: ignore[no-untyped-def]
    r = api.post("/stop", role="analyst")
    assert r.status_code == 202 and r.json()["halted"] is True and r.json()["scan_aborted"] is None

def test_one_scan_at_a_time_and_abort(api) -> None:  # type: ignore[no-untyped-def]
    scan_id = _start(api)
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 10})
    assert r.status_code == 409 and scan_id in r.json()["message"]
    assert api.post("/devices/hexapod/move", json={"targets": {"X": 1.0}}).status_code == 409
    assert api.get(f"/scans/{scan_id}/file").status_code == 409
    assert api.post("/calibrations", role="analyst", json={"scan_id": scan_id}).status_code == 409
    r = api.post(f"/scans/{scan_id}/pause")
    assert r.status_code == 202
    paused = wait_for(api, f"/scans/{scan_id}", lambda b: b["state"] == "paused", 30)
    n = paused["progress"]["done"]
    time.sleep(0.3)
    assert api.get(f"/scans/{scan_id}").json()["progress"]["done"] == n
    xray = api.get("/devices/xray").json()["state"]
    assert xray["exposing"] is False and xray["hv_on"] is False and xray["state"] == "IDLE"  # X-rays off while paused
    assert api.post(f"/scans/{scan_id}/resume").status_code == 202
    wait_for(api, f"/scans/{scan_id}", lambda b: b["progress"].get("done", 0) > n, 30)
    r = api.post(f"/scans/{scan_id}/abort", json={"reason": "sample slipped"})
    assert r.status_code == 202
    scan = wait_for(api, f"/scans/{scan_id}", ended, 30)
    assert scan["state"] == "aborted" and scan["reason"] == "sample slipped"
    assert api.post(f"/scans/{scan_id}/abort").status_code == 409
    r = api.post("/calibrations", role="analyst", json={"scan_id": scan_id})
    assert r.status_code == 409 and "aborted" in r.json()["message"]


def test_bench_process_crash_fails_the_scan_and_keeps_its_frames(api) -> None:  # type: ignore[no-untyped-def]
    scan_id = _start(api)
    api.service.rig._process.kill()
    scan = wait_for(api, f"/scans/{scan_id}", ended, 30)
    assert scan["state"] == "failed" and "bench process ended" in scan["reason"]
    assert scan["summary"]["status"] == "aborted" and scan["summary"]["n_frames"] >= 8
    assert api.get("/health", role=None).json() == {"status": "degraded", "version": api.get("/health").json()["version"],
                                                     "bench": "failed"}
    assert api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4}).status_code == 503
    r = api.post("/stop")
    assert r.status_code == 202 and r.json()["halted"] is False


def test_emergency_stop_halts_a_carm_scan(make_api, tmp_path) -> None:  # type: ignore[no-untyped-def]
    api = make_api(bench_config=small_carm_config(tmp_path))
    devices = [d["name"] for d in api.get("/devices").json()]
    assert devices == ["carm"]
    r = api.post("/scans", json={**SMALL_CARM_SAWTOOTH, "frames": 200})
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    running = wait_for(api, f"/scans/{scan_id}", lambda b: b["progress"].get("done", 0) >= 6 or ended(b))
    assert running["state"] == "running", running
    r = api.post("/stop", role="viewer")
    assert r.status_code == 202 and r.json()["halted"] is True and r.json()["scan_aborted"] == scan_id
    scan = wait_for(api, f"/scans/{scan_id}", ended, 30)
    assert scan["state"] == "aborted" and "emergency stop" in scan["reason"]
    state = api.get("/devices/carm").json()["state"]
    assert state["moving"] is False
    time.sleep(0.3)  # the arm stays where the stop left it
    assert api.get("/devices/carm").json()["state"]["primary_deg"] == state["primary_deg"]
    with ScanFile(api.data_dir / "scans" / f"{scan_id}.h5") as sf:
        assert sf.status == "aborted" and 6 <= sf.n_frames < 204
