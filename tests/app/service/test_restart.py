"""Restart recovery: a service killed during a scan comes back with the scan interrupted and its frames kept;
the orphaned bench process stops the hardware and exits."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import psutil
import pytest

from orbitct.scanfile import ScanFile
from tests.helpers.service import SMALL_SAWTOOTH, parse_sse, small_bench_config

pytestmark = pytest.mark.system

DEV = "oct_dev_token_for_restart_test"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _serve(tmp_path: Path, data: Path) -> tuple[subprocess.Popen[bytes], str, dict[str, str]]:
    """``orbitct serve --sim`` in a subprocess, once its rig is connected: the process, base URL and auth header."""
    port = _free_port()
    env = {**os.environ, "ORBITCT_DEV_TOKEN": DEV, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    proc = subprocess.Popen(
        [sys.executable, "-m", "orbitct_app.cli.main", "serve", "--config", str(small_bench_config(tmp_path)), "--sim",
         "--port", str(port), "--stop-port", "0", "--data-dir", str(data), "--log-level", "warning"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )
    base = f"http://127.0.0.1:{port}"
    t0 = time.monotonic()
    while True:
        try:
            if httpx.get(f"{base}/health", timeout=1).json()["bench"] == "connected":
                return proc, base, {"Authorization": f"Bearer {DEV}"}
        except (httpx.HTTPError, ValueError, KeyError):
            pass
        if proc.poll() is not None or time.monotonic() - t0 > 60:
            proc.kill()
            raise AssertionError("service did not start: " + proc.stderr.read().decode()[-2000:])  # type: ignore[union-attr]
        time.sleep(0.2)


def _scan_running(base: str, headers: dict[str, str], frames_done: int = 10) -> str:
    r = httpx.post(f"{base}/scans", json={**SMALL_SAWTOOTH, "frames": 300}, headers=headers, timeout=30)
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    while httpx.get(f"{base}/scans/{scan_id}", headers=headers, timeout=5).json()["progress"].get("done", 0) < frames_done:
        time.sleep(0.05)
    return str(scan_id)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_signal_stops_the_service_and_aborts_its_scan(make_api, tmp_path: Path, sig: signal.Signals) -> None:  # type: ignore[no-untyped-def]
    data = tmp_path / "data"
    make_api(data).client.__exit__(None, None, None)  # tokens made; the subprocess owns the data dir alone
    proc, base, headers = _serve(tmp_path, data)
    try:
        scan_id = _scan_running(base, headers)
        rig = psutil.Process(proc.pid).children()
        proc.send_signal(sig)
        proc.wait(60)
    finally:
        if proc.poll() is None:
            proc.kill()
    gone, alive = psutil.wait_procs(rig, timeout=30)
    assert not alive
    with ScanFile(data / "scans" / f"{scan_id}.h5") as sf:
        assert sf.status == "aborted" and sig.name in sf.status_reason, sf.status_reason
        assert sf.n_frames >= 10


@pytest.mark.slow
def test_sigkill_during_scan_then_restart(make_api, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    data = tmp_path / "data"
    api = make_api(data)  # creates the tokens; closed again below so the subprocess owns the data dir alone
    api.client.__exit__(None, None, None)
    proc, base, headers = _serve(tmp_path, data)
    try:
        scan_id = _scan_running(base, headers)
        bench = psutil.Process(proc.pid).children()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    # the orphaned bench process notices, halts the twins, closes the file and exits
    gone, alive = psutil.wait_procs(bench, timeout=30)
    assert not alive

    api2 = make_api(data)
    scan = api2.get(f"/scans/{scan_id}").json()
    assert scan["state"] == "interrupted" and "stopped while it was running" in scan["reason"]
    assert scan["summary"]["status"] == "aborted", scan["summary"]
    assert scan["summary"]["status_reason"] in ("interrupted", "the web service stopped (its process ended)")
    assert scan["summary"]["n_frames"] >= 10
    with ScanFile(data / "scans" / f"{scan_id}.h5") as sf:
        assert sf.status == "aborted" and sf.n_frames >= 10
    events = parse_sse(api2.get(f"/scans/{scan_id}/events").text)
    assert [e["id"] for e in events] == list(range(events[0]["id"], events[0]["id"] + len(events)))
    assert events[-1]["event"] == "end" and events[-1]["data"]["state"] == "interrupted"
    assert api2.post("/calibrations", role="analyst", json={"scan_id": scan_id}).status_code == 409
    # the bench is free for a new scan after the restart
    r = api2.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4})
    assert r.status_code == 202, r.text
