"""The emergency stop through the service: it latches, proves what it halted, survives a dead rig process, and only
an operator resets it; generator faults are reset the same deliberate way."""

from __future__ import annotations

import os
import signal
import time

import httpx
import pytest

from devices.xray_registers import FaultCode
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


def _safety_events(api) -> list[tuple[str, dict]]:  # type: ignore[no-untyped-def]
    events, _ = api.service.bus.since("safety", 0)
    return [(kind, data) for _, kind, data in events]


def test_emergency_stop_halts_proves_and_latches_until_an_operator_resets(api) -> None:  # type: ignore[no-untyped-def]
    scan_id = _start(api)
    r = api.post("/stop", role="viewer", json={"reason": "smoke near the tube"})  # anyone who sees the bench may stop
    assert r.status_code == 202, r.text
    body = r.json()
    assert body["halted"] is True and body["latched"] is True and body["via"] == "guard", body
    assert body["scan_aborted"] == scan_id and body["by"] == "test-viewer (viewer)"
    verified = {d["device"]: d["verified"] for d in body["devices"]}
    assert set(verified) == {"hexapod", "rotation_stage", "xray"}
    assert verified["xray"].startswith("high voltage off") and verified["hexapod"] == "axes not moving"
    scan = wait_for(api, f"/scans/{scan_id}", ended, 30)
    assert scan["state"] == "aborted" and "emergency stop" in scan["reason"] and "smoke near the tube" in scan["reason"]
    with ScanFile(api.data_dir / "scans" / f"{scan_id}.h5") as sf:
        assert sf.status == "aborted" and "emergency stop" in sf.status_reason and sf.n_frames >= 8

    # latched: nothing moves, nothing exposes, until an operator resets it
    for attempt in (
        lambda: api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4}),
        lambda: api.post("/devices/rotation_stage/move", json={"targets": {"R": 1.0}}),
        lambda: api.post("/devices/hexapod/reference"),
    ):
        refused = attempt()
        assert refused.status_code == 409 and "emergency stop latched by test-viewer" in refused.json()["message"]
    state = api.get("/stop").json()
    assert state["latched"] and state["by"] == "test-viewer (viewer)" and state["reason"] == "smoke near the tube"
    assert state["stop_url"].startswith("http://127.0.0.1:")
    assert api.get("/health", role=None).json()["estop"] == "latched"
    xray = api.get("/devices/xray").json()
    assert xray["estop_latched"] is True and xray["state"]["hv_on"] is False
    for name in ("hexapod", "rotation_stage"):
        assert api.get(f"/devices/{name}").json()["state"]["moving"] is False

    assert api.post("/stop/reset", role="viewer").status_code == 403
    assert api.post("/stop/reset", role="analyst").status_code == 403
    r = api.post("/stop/reset", json={"note": "tube checked"})
    assert r.status_code == 200 and r.json()["latched"] is False
    assert (
        r.json()["last_reset"]["by"] == "test-operator (operator)" and r.json()["last_reset"]["note"] == "tube checked"
    )
    assert api.post("/stop/reset").status_code == 409  # nothing latched any more
    assert api.get("/health", role=None).json()["estop"] == "clear"
    assert api.post("/devices/rotation_stage/move", json={"targets": {"R": 1.0}}).status_code == 200
    kinds = [k for k, _ in _safety_events(api)]
    assert kinds == ["stop", "reset"]


def test_stop_listener_of_its_own(api) -> None:  # type: ignore[no-untyped-def]
    url = api.get("/stop").json()["stop_url"]
    assert httpx.post(url).status_code == 401
    assert httpx.post(url, headers={"Authorization": "Bearer oct_not_a_token"}).status_code == 401
    r = httpx.post(url, headers=api.headers("analyst"), json={"reason": "drill"})
    assert r.status_code == 202 and r.json()["halted"] is True and r.json()["latched"] is True
    assert r.headers["access-control-allow-origin"] == "*"
    assert httpx.get(url, headers=api.headers("viewer")).json()["latched"] is True
    assert httpx.get(url.removesuffix("/stop") + "/health").json() == {"status": "ok", "latched": True}
    assert api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4}).status_code == 409
    wait_for(api, "/stop", lambda b: True)
    assert [k for k, _ in _safety_events(api)] == ["stop"]  # the guard told the web server
    assert api.post("/stop/reset").status_code == 200


def test_stop_latch_survives_a_restart(make_api) -> None:  # type: ignore[no-untyped-def]
    api = make_api()
    assert api.post("/stop").json()["latched"] is True
    api.client.__exit__(None, None, None)
    api2 = make_api(api.data_dir)
    assert api2.get("/stop").json()["latched"] is True
    assert api2.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4}).status_code == 409
    assert api2.post("/stop/reset").status_code == 200


def test_garbled_or_missing_stop_confirmation_is_not_halted(api) -> None:  # type: ignore[no-untyped-def]
    # every reply garbled while the stop runs (the rig's X-ray heartbeats would use up a small count first)
    api.service.sim_bench.hazard("xray", "faults.garble_next", 1000)
    try:
        body = api.post("/stop").json()
    finally:
        api.service.sim_bench.hazard("xray", "faults.garble_next", 0)
    assert body["halted"] is False and body["latched"] is True
    xray = next(d for d in body["devices"] if d["device"] == "xray")
    assert not xray["halted"] and "garbled" in xray["problem"] and "xray" in body["message"]
    assert body["message"].startswith("NOT verified")

    api.service.sim_bench.hazard("hexapod", "faults.latency_s", 3.0)  # no confirmation within the stop's bound
    try:
        body = api.post("/stop").json()
    finally:
        api.service.sim_bench.hazard("hexapod", "faults.latency_s", 0.0)
    hexapod = next(d for d in body["devices"] if d["device"] == "hexapod")
    assert body["halted"] is False and not hexapod["halted"] and "no reply" in hexapod["problem"], body


def test_rig_process_killed_is_restarted_and_the_stop_still_reaches_the_devices(api) -> None:  # type: ignore[no-untyped-def]
    scan_id = _start(api)
    os.kill(api.service.rig._process.pid, signal.SIGKILL)
    scan = wait_for(api, f"/scans/{scan_id}", ended, 30)
    assert scan["state"] == "failed" and "bench process ended" in scan["reason"]
    assert scan["summary"]["status"] == "aborted" and scan["summary"]["n_frames"] >= 8
    # meanwhile the guard still reaches every device over its own connections
    r = api.post("/stop")
    assert r.status_code == 202 and r.json()["halted"] is True and r.json()["via"] == "guard", r.json()
    health = wait_for(api, "/health", lambda b: b["bench"] == "connected", 60)
    assert health["guard"] == "listening" and health["estop"] == "latched"
    assert api.post("/stop/reset").status_code == 200
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 20})
    assert r.status_code == 202, r.text
    assert wait_for(api, f"/scans/{r.json()['id']}", ended, 60)["state"] == "complete"


def test_guard_killed_falls_back_to_the_rig_process_and_comes_back(api) -> None:  # type: ignore[no-untyped-def]
    os.kill(api.service.guard._process.pid, signal.SIGKILL)
    wait_for(api, "/health", lambda b: b["guard"] != "listening", 10, poll_s=0.01)
    body = api.post("/stop", role="viewer").json()
    assert body["halted"] is True and body["via"] == "rig" and body["latched"] is True, body
    assert "the guard is not listening" in body["message"]
    assert api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4}).status_code == 409
    wait_for(api, "/health", lambda b: b["guard"] == "listening", 60)
    assert api.post("/stop").json()["via"] == "guard"
    assert api.post("/stop/reset").status_code == 200


def test_one_scan_at_a_time_pause_and_abort(api) -> None:  # type: ignore[no-untyped-def]
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
    assert api.get("/stop").json()["latched"] is False  # an abort is not an emergency stop


def test_generator_fault_reset_by_an_operator_refused_while_its_cause_persists(api) -> None:  # type: ignore[no-untyped-def]
    bench = api.service.sim_bench
    bench.hazard("xray", "door", False)
    bench.hazard("xray", "fault", int(FaultCode.INTERLOCK_OPENED))
    state = wait_for(api, "/devices/xray", lambda b: b["state"]["state"] == "FAULT")["state"]
    assert state["fault"] == "INTERLOCK_OPENED" and state["hv_on"] is False
    assert api.post("/devices/xray/reset-fault", role="viewer").status_code == 403
    r = api.post("/devices/xray/reset-fault")
    assert r.status_code == 409 and "door interlock is still open" in r.json()["message"], r.text
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4})  # pre-flight refuses before anything moves
    assert r.status_code == 409 and "INTERLOCK_OPENED" in r.json()["message"], r.text
    bench.hazard("xray", "door", True)
    r = api.post("/devices/xray/reset-fault")
    assert r.status_code == 200 and r.json()["state"]["state"] == "IDLE", r.text

    bench.hazard("xray", "fault_input", True)  # an overtemperature input that stays asserted
    r = api.post("/devices/xray/reset-fault")
    assert r.status_code == 409 and "fault input is asserted" in r.json()["message"], r.text
    bench.hazard("xray", "fault_input", False)
    assert api.post("/devices/xray/reset-fault").json()["state"]["fault"] == "NONE"
    assert api.post("/devices/hexapod/reset-fault").status_code == 422


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
    body = r.json()
    assert r.status_code == 202 and body["halted"] is True and body["scan_aborted"] == scan_id, body
    assert [d["device"] for d in body["devices"]] == ["carm"] and body["devices"][0]["verified"] == "not moving"
    scan = wait_for(api, f"/scans/{scan_id}", ended, 30)
    assert scan["state"] == "aborted" and "emergency stop" in scan["reason"]
    state = api.get("/devices/carm").json()["state"]
    assert state["moving"] is False
    time.sleep(0.3)  # the arm stays where the stop left it
    assert api.get("/devices/carm").json()["state"]["primary_deg"] == state["primary_deg"]
    with ScanFile(api.data_dir / "scans" / f"{scan_id}.h5") as sf:
        assert sf.status == "aborted" and 6 <= sf.n_frames < 204
    assert api.post("/scans", json={**SMALL_CARM_SAWTOOTH, "frames": 20}).status_code == 409


def _exchange(sock, request: bytes) -> tuple[int, dict[str, str], bytes]:  # type: ignore[no-untyped-def]
    """Send one raw HTTP/1.1 request on ``sock`` and read one whole answer: status, headers, body."""
    sock.sendall(request)
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        assert chunk, f"the connection closed before an answer: {data!r}"
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    while len(body) < int(headers.get("content-length", 0)):
        body += sock.recv(65536)
    return int(lines[0].split()[1]), headers, body


def test_nothing_on_a_keep_alive_connection_swallows_the_stop_that_follows(api) -> None:  # type: ignore[no-untyped-def]
    import json
    import socket
    from urllib.parse import urlsplit

    url = urlsplit(api.get("/stop").json()["stop_url"])
    token = api.tokens["viewer"]
    reason = b'{"reason": "keep-alive"}'
    stop = (
        f"POST /stop HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(reason)}\r\n\r\n"
    ).encode() + reason
    body = b'{"some": "thing", "else": [1, 2, 3]}'
    first_requests = [
        b"POST /not-a-route HTTP/1.1\r\nHost: x\r\nContent-Length: %d\r\n\r\n" % len(body) + body,  # unknown route
        b"PUT /stop HTTP/1.1\r\nHost: x\r\nContent-Length: %d\r\n\r\n" % len(body) + body,  # a method it does not serve
        b"FROB /stop HTTP/1.1\r\nHost: x\r\nContent-Length: %d\r\n\r\n" % len(body) + body,  # one nobody serves
        b"POST /nothing HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n0\r\n\r\n",  # chunked
        b"GET /health HTTP/1.1\r\nHost: x\r\nContent-Length: %d\r\n\r\n" % len(body) + body,  # a GET with a body
    ]
    for first in first_requests:
        with socket.create_connection((url.hostname, url.port), timeout=10) as sock:
            status, headers, _ = _exchange(sock, first)
            assert status in (200, 404, 405) and headers.get("connection") != "close", (first[:20], status)
            status, _, reply = _exchange(sock, stop)
            assert status == 202, (first[:20], status, reply)
            assert json.loads(reply)["halted"] is True and json.loads(reply)["reason"] == "keep-alive"
    # a body too large to read closes its connection, and says so; a stop on a new connection is taken
    with socket.create_connection((url.hostname, url.port), timeout=10) as sock:
        status, headers, _ = _exchange(sock, b"POST /x HTTP/1.1\r\nHost: x\r\nContent-Length: 99999999\r\n\r\n")
        assert status == 413 and headers["connection"] == "close"
    # a stop whose body is not understood is taken all the same, and the reply says what was wrong
    bad = f"POST /stop HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\nContent-Length: 9\r\n\r\nnot json!".encode()
    with socket.create_connection((url.hostname, url.port), timeout=10) as sock:
        status, _, reply = _exchange(sock, bad)
        assert status == 202 and json.loads(reply)["halted"] is True and "not JSON" in json.loads(reply)["note"]
    assert api.post("/stop/reset").status_code == 200


def test_a_resume_after_a_stop_is_refused(api) -> None:  # type: ignore[no-untyped-def]
    scan_id = _start(api)
    assert api.post(f"/scans/{scan_id}/pause").status_code == 202
    wait_for(api, f"/scans/{scan_id}", lambda b: b["state"] == "paused", 30)
    assert api.post("/stop", role="viewer", json={"reason": "resume drill"}).json()["halted"] is True
    r = api.post(f"/scans/{scan_id}/resume")  # at once, before the scan has ended
    assert r.status_code == 409 and "emergency stop latched" in r.json()["message"], r.text
    scan = wait_for(api, f"/scans/{scan_id}", ended, 30)
    assert scan["state"] == "aborted" and "resume drill" in scan["reason"]
    assert api.post(f"/scans/{scan_id}/resume").status_code == 409
    assert api.post("/stop/reset").status_code == 200


def test_a_paused_scan_is_not_resumed_while_it_is_being_aborted(api) -> None:  # type: ignore[no-untyped-def]
    scan_id = _start(api)
    assert api.post(f"/scans/{scan_id}/pause").status_code == 202
    wait_for(api, f"/scans/{scan_id}", lambda b: b["state"] == "paused", 30)
    assert api.post(f"/scans/{scan_id}/abort", json={"reason": "abort drill"}).status_code == 202
    r = api.post(f"/scans/{scan_id}/resume")
    assert r.status_code == 409, r.text
    scan = wait_for(api, f"/scans/{scan_id}", ended, 30)
    assert scan["state"] == "aborted" and scan["reason"] == "abort drill"
