"""Restart recovery: a service killed during a scan comes back with the scan interrupted and its frames kept;
the orphaned bench process stops the hardware and exits."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import httpx
import psutil
import pytest

from orbitct.scanfile import ScanFile
from tests.helpers.service import (
    SMALL_SAWTOOTH,
    parse_sse,
    serve_subprocess,
    small_bench_config,
)

pytestmark = pytest.mark.system

DEV = "oct_dev_token_for_restart_test"


def _scan_running(base: str, headers: dict[str, str], frames_done: int = 10) -> str:
    r = httpx.post(f"{base}/scans", json={**SMALL_SAWTOOTH, "frames": 300}, headers=headers, timeout=30)
    assert r.status_code == 202, r.text
    scan_id = r.json()["id"]
    while (
        httpx.get(f"{base}/scans/{scan_id}", headers=headers, timeout=5).json()["progress"].get("done", 0) < frames_done
    ):
        time.sleep(0.05)
    return str(scan_id)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_signal_stops_the_service_and_aborts_its_scan(make_api, tmp_path: Path, sig: signal.Signals) -> None:  # type: ignore[no-untyped-def]
    data = tmp_path / "data"
    make_api(data).client.__exit__(None, None, None)  # tokens made; the subprocess owns the data dir alone
    proc, base, headers = serve_subprocess(small_bench_config(tmp_path), data, DEV)
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
    proc, base, headers = serve_subprocess(small_bench_config(tmp_path), data, DEV)
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
    assert scan["summary"]["status_reason"] in ("interrupted", "the service stopped (its web process ended)")
    assert scan["summary"]["n_frames"] >= 10
    assert scan["frames_done"] == scan["summary"]["n_frames"]  # the record follows the file
    with ScanFile(data / "scans" / f"{scan_id}.h5") as sf:
        assert sf.status == "aborted" and sf.n_frames >= 10
    events = parse_sse(api2.get(f"/scans/{scan_id}/events").text)
    assert [e["id"] for e in events] == list(range(events[0]["id"], events[0]["id"] + len(events)))
    assert events[-1]["event"] == "end" and events[-1]["data"]["state"] == "interrupted"
    assert api2.post("/calibrations", role="analyst", json={"scan_id": scan_id}).status_code == 409
    # the bench is free for a new scan after the restart
    r = api2.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4})
    assert r.status_code == 202, r.text


@pytest.mark.slow
def test_a_killed_service_leaves_no_worker_and_records_that_agree_with_the_file(make_api, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    data = tmp_path / "data"
    make_api(data).client.__exit__(None, None, None)
    proc, base, headers = serve_subprocess(small_bench_config(tmp_path), data, DEV)
    try:
        r = httpx.post(f"{base}/scans", json={**SMALL_SAWTOOTH, "frames": 20}, headers=headers, timeout=30)
        scan_id = r.json()["id"]
        while httpx.get(f"{base}/scans/{scan_id}", headers=headers, timeout=5).json()["state"] != "complete":
            time.sleep(0.1)
        r = httpx.post(
            f"{base}/reconstructions",
            headers=headers,
            timeout=30,
            json={
                "scan_id": scan_id,
                "algorithm": "pwls",
                "geometry": "nominal",
                "shape": [48, 64, 64],
                "iterations": 500,
            },
        )
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        pid = None
        while pid is None:
            for line in httpx.get(f"{base}/jobs/{job_id}/log", headers=headers, timeout=5).json():
                if "(pid " in line["line"]:
                    pid = int(line["line"].rsplit("(pid ", 1)[1].rstrip(")"))
            time.sleep(0.1)
        worker = psutil.Process(pid)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    gone, alive = psutil.wait_procs([worker], timeout=10)
    assert not alive, "the job worker outlived the service"

    api2 = make_api(data)
    job = api2.get(f"/jobs/{job_id}").json()
    assert job["state"] == "interrupted"
    with ScanFile(data / "scans" / f"{scan_id}.h5") as sf:
        assert sf.recon_names() == []  # the record says interrupted and the file holds no result
