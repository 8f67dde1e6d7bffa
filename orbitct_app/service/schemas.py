"""Response models shared by several routers (scans, jobs)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field

from orbitct_app.service.core.errors import Conflict, NotFound
from orbitct_app.service.core.files import confined


class Progress(BaseModel):
    """Latest progress of a scan or job."""

    stage: str = ""
    done: int = 0
    total: int = 0
    message: str = ""
    metrics: dict[str, float | None] = Field(default_factory=dict)
    expected_s: float | None = Field(
        None, description="how long the whole scan or job takes, measured on this machine, once it has said so"
    )


class VerdictOut(BaseModel):
    """The quality verdict of a calibration or reconstruction: a failed one ends its job as failed."""

    status: Literal["passed", "passed_with_warnings", "failed"]
    label: str = Field(description="the status as a person reads it")
    reasons: list[str] = Field(default_factory=list, description="why it failed")
    warnings: list[str] = Field(default_factory=list, description="what to read before using it")


class JobOut(BaseModel):
    """A calibration or reconstruction job."""

    id: str
    kind: str
    scan_id: str
    state: str = Field(description="queued, running, succeeded, failed, cancelled or interrupted")
    reason: str = ""
    error: str = Field(
        "",
        description="for a failed or interrupted job, its code in the error catalogue (failed_quality_check, "
        "action_failed, unavailable, conflict, interrupted, ...); empty otherwise",
    )
    params: dict[str, Any]
    progress: dict[str, Any]
    result: dict[str, Any]
    verdict: VerdictOut | None = Field(
        None, description="the result's quality verdict, once it has one (also when the job failed because of it)"
    )
    owner: str
    created_utc: str
    started_utc: str | None = None
    finished_utc: str | None = None
    links: dict[str, str] = Field(default_factory=dict)

    model_config = {
        "json_schema_extra": {
            "examples": [
                {
                    "id": "3f2a9c0d1b2e4f56",
                    "kind": "calibration",
                    "scan_id": "a1b2c3d4e5f60718",
                    "state": "running",
                    "reason": "",
                    "params": {"method": "bundle"},
                    "progress": {
                        "stage": "estimate",
                        "done": 2,
                        "total": 5,
                        "message": "",
                        "metrics": {"rpe_mean_mm": 0.08},
                    },
                    "result": {},
                    "owner": "analyst-1",
                    "created_utc": "2026-11-23T15:00:00.000+00:00",
                    "started_utc": "2026-11-23T15:00:01.000+00:00",
                    "finished_utc": None,
                    "links": {"self": "/jobs/3f2a9c0d1b2e4f56", "events": "/jobs/3f2a9c0d1b2e4f56/events"},
                }
            ]
        }
    }


def job_out(job: dict[str, Any]) -> JobOut:
    """API view of a job row."""
    base = "/calibrations" if job["kind"] == "calibration" else "/reconstructions"
    links = {
        "self": f"{base}/{job['id']}",
        "job": f"/jobs/{job['id']}",
        "events": f"/jobs/{job['id']}/events",
        "log": f"/jobs/{job['id']}/log",
        "scan": f"/scans/{job['scan_id']}",
    }
    verdict = (job.get("result") or {}).get("verdict")
    return JobOut(
        **{k: job[k] for k in JobOut.model_fields if k in job and k not in ("links", "verdict")},
        verdict=VerdictOut.model_validate(verdict) if verdict else None,
        links=links,
    )


def job_or_404(service: Any, job_id: str, kind: str | None = None) -> dict[str, Any]:
    """The job row, or 404 if unknown (or of another kind)."""
    job = service.store.get_job(job_id) if len(job_id) <= 64 else None
    if job is None or (kind is not None and job["kind"] != kind):
        raise NotFound(f"no {kind or 'job'} with id {job_id[:64]!r}")
    return job


def scan_or_404(service: Any, scan_id: str) -> dict[str, Any]:
    """The scan row, or 404 if unknown."""
    scan = service.store.get_scan(scan_id) if len(scan_id) <= 64 else None
    if scan is None:
        raise NotFound(f"no scan with id {scan_id[:64]!r}")
    return scan


def ended_scan_file(service: Any, scan_id: str, then: str) -> Path:
    """The file of a scan that has ended and that no job writes to; 404 if unknown, 409 (advice: ``then`` "when it
    has ended") otherwise."""
    row = scan_or_404(service, scan_id)
    if row["state"] in ("queued", "running", "paused") or service.rig.busy == scan_id:
        raise Conflict(f"scan {scan_id} is still {row['state']}", advice=f"{then} when it has ended")
    if scan_id in service.jobs.busy_scans():
        raise Conflict(f"a job is writing to scan {scan_id}", advice=f"{then} when the job has ended")
    folder, name = row["file"].split("/")
    return confined(service.settings.data_dir / folder, name)
