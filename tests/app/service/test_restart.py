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


@pytest.mark.slow
def test_sigkill_during_scan_then_restart(make_api, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    data = tmp_path / "data"
    api = make_api(data)  # creates the tokens; closed again below so the subprocess owns the data dir alone
    api.client.__exit__(None, None, None)
    port = _free_port()
    env = {**os.environ, "ORBITCT_DEV_TOKEN": DEV, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    proc = subprocess.Popen(
        [sys.executable, "-m", "orbitct_app.cli.main", "serve", "--config", str(small_bench_config(tmp_path)), "--sim",
         "--port", str(port), "--data-dir", str(data), "--log-level", "warning"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )
    base, headers = f"http://127.0.0.1:{port}", {"Authorization": f"Bearer {DEV}"}
    try:
        t0 = time.monotonic()
        while True:
            try:
                if httpx.get(f"{base}/health", timeout=1).json()["bench"] == "connected":
                    break
            except (httpx.HTTPError, ValueError, KeyError):
                pass
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]  # type: ignore[union-attr]
            assert time.monotonic() - t0 < 60, "service did not start"
            time.sleep(0.2)
        r = httpx.post(f"{base}/scans", json={**SMALL_SAWTOOTH, "frames": 300}, headers=headers, timeout=30)
        assert r.status_code == 202, r.text
        scan_id = r.json()["id"]
        while httpx.get(f"{base}/scans/{scan_id}", headers=headers, timeout=5).json()["progress"].get("done", 0) < 10:
            time.sleep(0.05)
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
