"""``/calibrations``: geometric calibration jobs on a scan and their results (RPE table, plots)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict, Field

from calib.options import CalibrationOptions
from orbitct_app.service.core.errors import (
    DISK_FULL,
    ERROR_RESPONSES,
    NOT_SUCCEEDED,
    Conflict,
    ErrorBody,
    NotFound,
)
from orbitct_app.service.core.files import confined
from orbitct_app.service.deps import Analyst, Reader, ServiceDep
from orbitct_app.service.schemas import JobOut, job_or_404, job_out, scan_or_404

router = APIRouter(prefix="/calibrations", tags=["calibrations"], responses=ERROR_RESPONSES)
ScanId = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")]


class CalibrationRequest(CalibrationOptions):
    """Calibrate a complete scan from the BBs on the object: the scan, and the options ``orbitct calibrate`` and
    Python take."""

    model_config = ConfigDict(
        strict=True,
        json_schema_extra={"examples": [{"scan_id": "a1b2c3d4e5f60718", "method": "bundle"}]},
    )

    scan_id: ScanId


def check_scan_ready(service: Any, scan_id: str) -> dict[str, Any]:
    """The scan, if jobs may run on it: 404 when unknown, 409 unless it is complete."""
    scan = scan_or_404(service, scan_id)
    if scan["state"] in ("queued", "running", "paused"):
        raise Conflict(f"scan {scan_id} is still {scan['state']}", advice="start the job when the scan is complete")
    if scan["state"] != "complete":
        reason = f" ({scan['reason']})" if scan["reason"] else ""
        raise Conflict(
            f"scan {scan_id} is {scan['state']}{reason}",
            advice="jobs need a complete scan: resume it if it is paused, or scan again",
        )
    return scan


def submit(service: Any, kind: str, request: BaseModel, owner: str, response: Response) -> JobOut:
    """Queue a job on a ready scan; 202 with its Location."""
    params = request.model_dump(exclude={"scan_id"}, exclude_none=True)
    job_id = service.jobs.submit(kind, request.scan_id, params, owner)  # type: ignore[attr-defined]
    out = job_out(service.store.get_job(job_id))
    response.headers["Location"] = out.links["self"]
    return out


@router.post(
    "",
    response_model=JobOut,
    status_code=202,
    summary="Start a calibration job",
    responses={
        409: {"model": ErrorBody, "description": "the scan is not complete (running, aborted, interrupted)"},
        **DISK_FULL,
    },
)
def start_calibration(body: CalibrationRequest, service: ServiceDep, who: Analyst, response: Response) -> JobOut:
    """Queue a calibration of the scan; progress on ``/jobs/{id}/events``."""
    check_scan_ready(service, body.scan_id)
    return submit(service, "calibration", body, who.name, response)


@router.get("", response_model=list[JobOut], summary="List calibration jobs")
def list_calibrations(
    service: ServiceDep,
    _: Reader,
    scan_id: Annotated[str | None, Query(max_length=64)] = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 100,
) -> list[JobOut]:
    """Calibration jobs, newest first."""
    return [job_out(j) for j in service.store.list_jobs(kind="calibration", scan_id=scan_id, limit=limit)]


@router.get("/{job_id}", response_model=JobOut, summary="A calibration job and its result summary")
def get_calibration(job_id: str, service: ServiceDep, _: Reader) -> JobOut:
    """State, progress and, once done, the Table-1 figures and RPE per iteration."""
    return job_out(job_or_404(service, job_id, "calibration"))


class RpeTable(BaseModel):
    """RPE like the paper's Table 1, per iteration, and per frame."""

    table: dict[str, Any]
    iterations: list[dict[str, Any]]
    per_frame_mm: dict[str, float]


@router.get(
    "/{job_id}/rpe", response_model=RpeTable, summary="RPE table of a finished calibration", responses=NOT_SUCCEEDED
)
def get_rpe(job_id: str, service: ServiceDep, _: Reader) -> RpeTable:
    """Table-1 figures, RPE statistics per iteration, and the RPE of every projection frame (mm)."""
    job = _finished(service, job_id)
    per_frame: dict[str, float] = {}
    path = confined(service.jobs.job_dir(job_id), "rpe_per_frame.csv")
    for line in path.read_text(encoding="utf-8").splitlines()[1:]:
        frame, value = line.split(",")
        per_frame[frame] = float(value)
    return RpeTable(
        table=job["result"].get("table", {}), iterations=job["result"].get("iterations", []), per_frame_mm=per_frame
    )


@router.get(
    "/{job_id}/files", response_model=list[str], summary="Report files (plots, tables)", responses=NOT_SUCCEEDED
)
def list_files(job_id: str, service: ServiceDep, _: Reader) -> list[str]:
    """Names of the report files: violin plots, per-view corrections, Table 1 (Markdown, CSV)."""
    return list(_finished(service, job_id)["result"].get("files", []))


@router.get(
    "/{job_id}/files/{name}",
    response_class=FileResponse,
    summary="One report file",
    responses={200: {"content": {"image/png": {}, "text/csv": {}, "text/markdown": {}}}, **NOT_SUCCEEDED},
)
def get_file(job_id: str, name: str, service: ServiceDep, _: Reader) -> FileResponse:
    """A plot (PNG) or table of the report; names come from ``/files``."""
    _finished(service, job_id)
    return FileResponse(confined(service.jobs.job_dir(job_id), name))


def _finished(service: Any, job_id: str) -> dict[str, Any]:
    """The job, once it has a report: succeeded, or failed by its quality check (the report says why)."""
    job = job_or_404(service, job_id, "calibration")
    judged = job["state"] == "failed" and bool((job.get("result") or {}).get("verdict"))
    if job["state"] != "succeeded" and not judged:
        raise Conflict(
            f"calibration {job_id} is {job['state']}",
            advice="ask again once it has finished (succeeded, or failed its quality check); then it has a report",
        )
    if not isinstance(job["result"], dict):
        raise NotFound(f"calibration {job_id} has no result")
    return job
