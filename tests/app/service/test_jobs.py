"""The job framework: worker processes, progress in order, log, failure, cancel, and restart recovery."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from orbitct_app.service.jobs import manager as jobs_module
from tests.helpers.service import parse_sse, write_small_scan
from tests.helpers.workloads import frame_means

pytestmark = pytest.mark.system


def _complete_scan(api: Any, scan_id: str = "s0000000000000001", n: int = 6) -> str:
    rel = f"scans/{scan_id}.h5"
    write_small_scan(api.data_dir / rel, n=n)
    api.service.store.add_scan(scan_id, name="small", orbit="circular", request={}, file=rel, owner="t", frames_total=n)
    api.service.store.update_scan(scan_id, state="complete", summary={"geometries": ["nominal"]})
    return scan_id


def _wait(
    api: Any,
    job_id: str,
    states: tuple[str, ...] = ("succeeded", "failed", "cancelled", "interrupted"),
    timeout_s: float = 60.0,
) -> dict[str, Any]:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        job = api.get(f"/jobs/{job_id}").json()
        if job["state"] in states:
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} still {job['state']}")


@pytest.fixture
def workload(monkeypatch: pytest.MonkeyPatch) -> None:
    """Calibration jobs run the small frame-means workload instead of the BB calibration."""
    monkeypatch.setitem(jobs_module.JOB_TARGETS, "calibration", frame_means)


def test_job_runs_in_a_worker_with_ordered_progress(api, workload) -> None:  # type: ignore[no-untyped-def]
    scan_id = _complete_scan(api)
    r = api.post("/calibrations", role="analyst", json={"scan_id": scan_id})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    assert r.headers["location"] == f"/calibrations/{job_id}"
    job = _wait(api, job_id)
    assert job["state"] == "succeeded", job
    assert job["result"]["n"] == 8 and job["progress"]["done"] == 8
    means = np.load(api.data_dir / "jobs" / job_id / "means.npy")
    assert means[2] == pytest.approx(100.0)
    events = parse_sse(api.get(f"/jobs/{job_id}/events").text)
    assert [e["id"] for e in events] == list(range(1, len(events) + 1))
    progress = [e["data"]["done"] for e in events if e["event"] == "progress"]
    assert progress == list(range(1, 9))
    assert [e["event"] for e in events][-1] == "end" and events[-1]["data"]["state"] == "succeeded"
    states = [e["data"]["state"] for e in events if e["event"] == "state"]
    assert states == ["queued", "running", "succeeded"]
    # resume after an id
    later = parse_sse(api.get(f"/jobs/{job_id}/events", headers={"Last-Event-ID": str(events[-3]["id"])}).text)
    assert [e["id"] for e in later] == [e["id"] for e in events[-2:]]
    for odd in (b"\xb2", b"-1", b"1e3", b" 7", b"x" * 20):  # not an id (b"\xb2" is "²"): the whole stream again
        again = api.get(f"/jobs/{job_id}/events", headers={"Last-Event-ID": odd})
        assert again.status_code == 200 and len(parse_sse(again.text)) == len(events), odd
    log = [line["line"] for line in api.get(f"/jobs/{job_id}/log").json()]
    assert log[0].startswith("started calibration") and log[-1] == "succeeded"


def test_job_failure_is_reported_without_internals(api, workload, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    scan_id = _complete_scan(api)
    job_id = api.service.jobs.submit("calibration", scan_id, {"fail": True}, "t")
    job = _wait(api, job_id)
    assert job["state"] == "failed" and "asked to fail" in job["reason"]
    assert job["error"] == "action_failed", job  # the catalogue's code, for scripts
    assert str(api.data_dir.resolve()) not in job["reason"]
    assert "Traceback" not in " ".join(line["line"] for line in api.get(f"/jobs/{job_id}/log").json())


def test_cancel_running_and_queued_jobs(api, workload) -> None:  # type: ignore[no-untyped-def]
    scan_id = _complete_scan(api, n=40)
    first = api.service.jobs.submit("calibration", scan_id, {"delay_s": 0.2}, "t")
    second = api.service.jobs.submit("calibration", scan_id, {}, "t")
    _wait(api, first, ("running",))
    assert api.get(f"/jobs/{second}").json()["state"] == "queued"  # one job per scan file at a time
    r = api.post(f"/jobs/{second}/cancel", role="analyst")
    assert r.status_code == 202 and r.json()["state"] == "cancelled"
    r = api.post(f"/jobs/{first}/cancel", role="analyst")
    assert r.status_code == 202
    job = _wait(api, first)
    assert job["state"] == "cancelled"
    assert api.post(f"/jobs/{first}/cancel", role="analyst").status_code == 409


def test_jobs_only_on_complete_scans(api) -> None:  # type: ignore[no-untyped-def]
    scan_id = _complete_scan(api)
    api.service.store.update_scan(scan_id, state="aborted", reason="emergency stop")
    r = api.post("/calibrations", role="analyst", json={"scan_id": scan_id})
    assert r.status_code == 409 and "aborted" in r.json()["message"]
    assert api.post("/calibrations", role="analyst", json={"scan_id": "f" * 16}).status_code == 404
    r = api.post("/reconstructions", role="analyst", json={"scan_id": scan_id, "algorithm": "fdk"})
    assert r.status_code == 409


def test_restart_marks_running_job_interrupted(make_api, workload) -> None:  # type: ignore[no-untyped-def]
    api = make_api()
    scan_id = _complete_scan(api, n=40)
    job_id = api.service.jobs.submit("calibration", scan_id, {"delay_s": 0.2}, "t")
    _wait(api, job_id, ("running",))
    # the process dies without shutting down: simulate by leaving the row 'running' and restarting on the same data
    api.service.jobs._stop.set()
    api.client.__exit__(None, None, None)
    store_state = api.service.store.get_job(job_id)["state"]
    assert store_state == "interrupted"  # a clean shutdown marks it too
    api.service.store.update_job(job_id, state="running", reason="")  # as if the process had been killed
    api2 = make_api(api.data_dir)
    job = api2.get(f"/jobs/{job_id}").json()
    assert job["state"] == "interrupted" and "stopped while it was running" in job["reason"]
    events = parse_sse(api2.get(f"/jobs/{job_id}/events").text)
    assert events[-1]["event"] == "end" and events[-1]["data"]["state"] == "interrupted"


def test_a_reconstruction_estimated_above_the_limit_fails_at_once_with_the_estimate(api) -> None:  # type: ignore[no-untyped-def]
    scan_id = _complete_scan(api)
    r = api.post(
        "/reconstructions",
        role="analyst",
        json={
            "scan_id": scan_id,
            "geometry": "nominal",
            "algorithm": "pwls",
            "shape": [16, 24, 24],
            "iterations": 50,
            "max_minutes": 1e-6,
        },
    )
    assert r.status_code == 202, r.text
    job = _wait(api, r.json()["id"])
    assert (
        job["state"] == "failed" and "is estimated to take" in job["reason"] and "more than the limit" in job["reason"]
    ), job
    assert job["params"]["max_minutes"] == 1e-6
    r = api.post(
        "/reconstructions",
        role="analyst",
        json={"scan_id": scan_id, "geometry": "nominal", "algorithm": "fdk", "shape": [16, 24, 24]},
    )
    job = _wait(api, r.json()["id"])  # the service's limit (60 min by default) lets it through
    assert job["state"] == "succeeded" and job["params"]["max_minutes"] == 60.0 and job["result"]["estimated_s"] > 0, (
        job
    )
