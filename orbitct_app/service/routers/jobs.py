"""``/jobs``: state, progress, log, live events and cancellation of calibration and reconstruction jobs."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query
from pydantic import BaseModel

from orbitct_app.service.core.errors import (
    DISK_FULL,
    ERROR_RESPONSES,
    Conflict,
    ErrorBody,
)
from orbitct_app.service.core.events import sse_response
from orbitct_app.service.deps import Analyst, Reader, ServiceDep
from orbitct_app.service.schemas import JobOut, job_or_404, job_out

router = APIRouter(prefix="/jobs", tags=["jobs"], responses=ERROR_RESPONSES)
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled", "interrupted"]


class LogLine(BaseModel):
    """One line of a job's log."""

    seq: int
    time_utc: str
    line: str


class CancelOut(BaseModel):
    """What a cancel request did."""

    id: str
    state: str


@router.get("", response_model=list[JobOut], summary="List jobs")
def list_jobs(
    service: ServiceDep,
    _: Reader,
    kind: Literal["calibration", "reconstruction"] | None = None,
    scan_id: Annotated[str | None, Query(max_length=64)] = None,
    state: JobState | None = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
) -> list[JobOut]:
    """Jobs, newest first."""
    return [
        job_out(j) for j in service.store.list_jobs(kind=kind, scan_id=scan_id, state=state, limit=limit, offset=offset)
    ]


@router.get("/{job_id}", response_model=JobOut, summary="State and progress of a job")
def get_job(job_id: str, service: ServiceDep, _: Reader) -> JobOut:
    """State, latest progress and (when done) the result summary."""
    return job_out(job_or_404(service, job_id))


@router.get("/{job_id}/log", response_model=list[LogLine], summary="Log of a job")
def get_log(
    job_id: str,
    service: ServiceDep,
    _: Reader,
    after: Annotated[int, Query(ge=0, le=10**9)] = 0,
    limit: Annotated[int, Query(ge=1, le=5000)] = 1000,
) -> list[LogLine]:
    """Log lines after sequence number ``after``."""
    job_or_404(service, job_id)
    return [LogLine(**row) for row in service.store.job_log(job_id, after=after, limit=limit)]


@router.get(
    "/{job_id}/events",
    summary="Live progress (server-sent events)",
    responses={
        200: {
            "content": {
                "text/event-stream": {
                    "example": 'id: 3\nevent: progress\ndata: {"stage":"pwls","done":3,"total":50,"metrics":{"cost":12.5}}\n\n'
                }
            }
        }
    },
)
def job_events(
    job_id: str, service: ServiceDep, _: Reader, last_event_id: Annotated[str | None, Header(max_length=20)] = None
):
    """Events ``state``, ``progress`` and a final ``end``, in order; resumes after ``Last-Event-ID``."""
    job_or_404(service, job_id)
    return sse_response(service.bus, f"job:{job_id}", last_event_id)


@router.post(
    "/{job_id}/cancel",
    response_model=CancelOut,
    status_code=202,
    summary="Cancel a job",
    responses={409: {"model": ErrorBody, "description": "the job has already ended"}, **DISK_FULL},
)
def cancel_job(job_id: str, service: ServiceDep, _: Analyst) -> CancelOut:
    """Cancel a queued or running job (a running worker gets a grace period, then is killed)."""
    job = job_or_404(service, job_id)
    if job["state"] not in ("queued", "running"):
        raise Conflict(f"job {job_id} has already ended ({job['state']})", advice="there is nothing to cancel")
    return CancelOut(id=job_id, state=service.jobs.cancel(job_id))
