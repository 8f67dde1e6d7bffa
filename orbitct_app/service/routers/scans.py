"""``/scans``: start (one at a time per bench), list, status with summary, live events, pause, abort, download."""

from __future__ import annotations

import asyncio
import time
import uuid
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Query, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from acquire.options import ScanOptions
from orbitct.orbits import ORBIT_KINDS
from orbitct_app.live_options import LiveCalibrationOptions
from orbitct_app.service.core.errors import (
    BENCH_UNAVAILABLE,
    DISK_FULL,
    ERROR_RESPONSES,
    Conflict,
    ErrorBody,
    FieldProblem,
    Invalid,
    StopLatched,
    validation_details,
)
from orbitct_app.service.core.events import sse_response
from orbitct_app.service.core.schema_rules import only_with, schema_extra
from orbitct_app.service.deps import Reader, ScanOperator, ServiceDep
from orbitct_app.service.schemas import VerdictOut, ended_scan_file, scan_or_404

router = APIRouter(prefix="/scans", tags=["scans"], responses=ERROR_RESPONSES)
ScanState = Literal["queued", "running", "paused", "complete", "aborted", "failed", "interrupted"]


class ScanCreate(ScanOptions, LiveCalibrationOptions):
    """A scan to run on the bench (:class:`acquire.options.ScanOptions`, the orbit's parameters as ``params``),
    with a label and live calibration."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        allow_inf_nan=False,
        populate_by_name=False,
        json_schema_extra=schema_extra(
            [
                {
                    "name": "experiment A",
                    "orbit": "sawtooth",
                    "params": {"amplitude_deg": 6, "cycles": 2},
                    "frames": 500,
                    "errors": "none",
                    "seed": 0,
                    "mode": "step",
                }
            ],
            only_with("abort_on", "calibrate", "live"),
        ),
    )

    name: str = Field("", max_length=100, pattern=r"^[\w .,:()+-]*$", description="free label")
    orbit_params: dict[str, Any] = Field(
        default_factory=dict, alias="params", description="orbit parameters (degrees), see GET /orbits/{kind}"
    )


class ScanCalibration(BaseModel):
    """A scan's latest calibration: the job that made it (none for a live calibration), its state and verdict."""

    job_id: str | None = None
    state: str = Field(description="the job's state, or 'live' for a calibration made during the scan")
    verdict: VerdictOut | None = None


class ScanOut(BaseModel):
    """A scan: state, progress (live while it runs), summary of the file (once ended)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "a1b2c3d4e5f60718",
                    "name": "experiment A",
                    "state": "running",
                    "reason": "",
                    "orbit": "sawtooth",
                    "request": {"orbit": "sawtooth", "frames": 500},
                    "owner": "operator-1",
                    "created_utc": "2026-11-23T15:00:00.000+00:00",
                    "started_utc": "2026-11-23T15:00:00.100+00:00",
                    "finished_utc": None,
                    "frames_done": 120,
                    "frames_total": 500,
                    "progress": {
                        "stage": "scan",
                        "done": 120,
                        "total": 500,
                        "message": "",
                        "metrics": {"rate_fps": 28.5, "time_left_s": 13.3},
                    },
                    "summary": {},
                    "links": {"self": "/scans/a1b2c3d4e5f60718", "events": "/scans/a1b2c3d4e5f60718/events"},
                }
            ]
        }
    )

    id: str
    name: str
    state: str = Field(description="queued, running, paused, complete, aborted, failed or interrupted")
    reason: str
    orbit: str
    request: dict[str, Any]
    owner: str
    created_utc: str
    started_utc: str | None
    finished_utc: str | None
    frames_done: int = Field(description="frames written so far (projections, darks and flats)")
    frames_total: int = Field(description="frames planned (projections, darks and flats once the scan has started)")
    progress: dict[str, Any]
    summary: dict[str, Any]
    calibration: ScanCalibration | None = Field(
        None, description="its latest calibration (a job, or the live one of the scan) and that one's verdict"
    )
    links: dict[str, str]


class ScanAction(BaseModel):
    """Why (optional) for abort."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)
    reason: str = Field("aborted by the operator", max_length=200)


def _latest_calibration(service: Any, scan_id: str) -> dict[str, Any] | None:
    jobs = service.store.list_jobs(kind="calibration", scan_id=scan_id, limit=1)
    return jobs[0] if jobs else None


def _calibration(row: dict[str, Any], job: dict[str, Any] | None) -> ScanCalibration | None:
    """The scan's latest calibration job, or else the live calibration its file holds."""
    if job is not None:
        verdict = (job.get("result") or {}).get("verdict")
        return ScanCalibration(
            job_id=job["id"], state=job["state"], verdict=VerdictOut.model_validate(verdict) if verdict else None
        )
    live = (row.get("summary") or {}).get("calibration") or {}
    if live.get("verdict"):
        return ScanCalibration(state="live", verdict=VerdictOut.model_validate(live["verdict"]))
    return None


def _out(service: Any, row: dict[str, Any], calibration_job: dict[str, Any] | None = None) -> ScanOut:
    active = service.rig.current
    if active is not None and active.scan_id == row["id"] and row["state"] not in ("complete", "aborted", "failed"):
        progress = active.progress
        row = {
            **row,
            "state": active.state,
            "progress": progress,
            "frames_done": progress.get("done", row["frames_done"]),
            "frames_total": progress.get("total", row["frames_total"]),
        }
    links = {
        "self": f"/scans/{row['id']}",
        "events": f"/scans/{row['id']}/events",
        "file": f"/scans/{row['id']}/file",
        "jobs": f"/jobs?scan_id={row['id']}",
    }
    return ScanOut(
        **{k: row[k] for k in ScanOut.model_fields if k not in ("links", "calibration")},
        calibration=_calibration(row, calibration_job),
        links=links,
    )


def _check_params(service: Any, body: ScanCreate) -> dict[str, Any]:
    params = dict(body.orbit_params)
    if body.frames is not None:
        params["n_frames"] = body.frames
    if body.orbit == "waypoints" and params.get("path") is not None:
        raise Invalid(
            "orbit parameters",
            details=[
                FieldProblem(
                    field="params.path", reason="server file paths are not accepted over the API; give 'points'"
                )
            ],
        )
    try:
        model = ORBIT_KINDS[body.orbit].model_validate(params)
    except ValidationError as exc:
        details = [
            FieldProblem(field="params." + d.field, reason=d.reason) for d in validation_details(list(exc.errors()))
        ]
        raise Invalid("; ".join(f"{d.field}: {d.reason}" for d in details[:5]), details=details) from None
    n = int(model.n_frames)
    limit = service.settings.max_scan_frames
    if n > limit:
        raise Invalid(
            f"{n} frames is more than this service allows ({limit})",
            advice=f"ask for at most {limit} frames (the service setting max_scan_frames sets the limit)",
            details=[FieldProblem(field="frames", reason=f"at most {limit}")],
        )
    return model.model_dump(mode="json", exclude_none=True)


def _preflight(service: Any, body: ScanCreate, params: dict[str, Any], rel: str) -> dict[str, Any]:
    """The bench's pre-flight of the scan (every frame against every axis limit, room on the disk); its spec."""
    spec = {
        "out": str(service.settings.data_dir / rel),
        "orbit": body.orbit,
        "params": params,
        "errors": body.errors,
        "error_params": dict(body.error_params),
        "seed": body.seed,
        "mode": body.mode,
        "frame_rate_hz": body.frame_rate_hz,
        "calibrate": body.calibrate,
        "bb_diameter_mm": body.bb_diameter_mm,
        "abort_on": list(body.abort_on),
        "lost_frames": body.lost_frames,
    }
    try:
        service.rig.preflight(spec)
    except Invalid as exc:
        raise Invalid(exc.message, details=[FieldProblem(field="params", reason=exc.message)]) from None
    return spec


class PreflightOut(BaseModel):
    """A scan the bench could run now: nothing moved."""

    frames: int
    message: str


@router.post(
    "/preflight",
    response_model=PreflightOut,
    summary="Check a scan before anything moves",
    responses={**BENCH_UNAVAILABLE, 507: {"model": ErrorBody, "description": "the scan would not fit on the disk"}},
)
def preflight_scan(body: ScanCreate, service: ServiceDep, _: Reader) -> PreflightOut:
    """Plan the scan and check every frame against every axis limit and the disk's room, as starting it would; 422
    names the first infeasible frame and axis. Nothing moves, and a later start checks again."""
    params = _check_params(service, body)
    _preflight(service, body, params, f"scans/preflight-{uuid.uuid4().hex[:8]}.h5")
    n = int(params["n_frames"])
    return PreflightOut(
        frames=n, message=f"all {n} frames are within the limits of every axis, and the scan fits on the disk"
    )


@router.post(
    "",
    response_model=ScanOut,
    status_code=202,
    summary="Start a scan",
    responses={
        409: {
            "model": ErrorBody,
            "description": "the bench is busy with another scan, or an emergency stop is latched",
        },
        **BENCH_UNAVAILABLE,
        507: {
            "model": ErrorBody,
            "description": "the scan would not fit on the data directory's disk with the reserve "
            "(storage.reserve_mb) left: the message gives the numbers",
        },
        202: {"headers": {"Location": {"description": "URL of the new scan", "schema": {"type": "string"}}}},
    },
)
def start_scan(body: ScanCreate, service: ServiceDep, who: ScanOperator, response: Response) -> ScanOut:
    """Check the orbit against every limit, then start it; returns at once (progress on ``/scans/{id}/events``)."""
    params = _check_params(service, body)
    refused = service.estop.refusal("scans")
    if refused:
        raise StopLatched(refused)
    if service.rig.busy is not None:
        raise Conflict(
            f"the bench is busy with scan {service.rig.busy}", advice="start this one when it has ended (one at a time)"
        )
    scan_id = uuid.uuid4().hex[:16]
    rel = f"scans/{scan_id}.h5"
    spec = _preflight(service, body, params, rel)
    service.store.add_scan(
        scan_id,
        name=body.name,
        orbit=body.orbit,
        request=body.model_dump(mode="json", by_alias=True) | {"params": params},
        file=rel,
        owner=who.name,
        frames_total=int(params["n_frames"]),
    )
    try:
        service.rig.start_scan(scan_id, spec)
    except Exception:
        service.store.delete_scan(scan_id)
        raise
    response.headers["Location"] = f"/scans/{scan_id}"
    return _out(service, scan_or_404(service, scan_id))


@router.get("", response_model=list[ScanOut], summary="List scans")
def list_scans(
    service: ServiceDep,
    _: Reader,
    state: ScanState | None = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
) -> list[ScanOut]:
    """Scans, newest first."""
    return [
        _out(service, r, _latest_calibration(service, r["id"]))
        for r in service.store.list_scans(state=state, limit=limit, offset=offset)
    ]


@router.get("/{scan_id}", response_model=ScanOut, summary="Status and summary of a scan")
async def get_scan(scan_id: str, service: ServiceDep, _: Reader) -> ScanOut:
    """State, live progress (frame n of N, rate, time left) and, once ended, the file summary."""
    return _out(service, scan_or_404(service, scan_id), _latest_calibration(service, scan_id))


@router.get(
    "/{scan_id}/events",
    summary="Live progress (server-sent events)",
    responses={
        200: {
            "content": {
                "text/event-stream": {
                    "example": 'id: 7\nevent: progress\ndata: {"stage":"scan","done":5,"total":500,"metrics":{"rate_fps":29.8,"time_left_s":16.6}}\n\n'
                }
            }
        }
    },
)
def scan_events(
    scan_id: str, service: ServiceDep, _: Reader, last_event_id: Annotated[str | None, Header(max_length=20)] = None
):
    """Events ``state``, ``progress`` (one per frame) and a final ``end``, in order; resumes after ``Last-Event-ID``."""
    scan_or_404(service, scan_id)
    return sse_response(service.bus, f"scan:{scan_id}", last_event_id)


class FrameOut(BaseModel):
    """The newest frame of a running scan, small and 8-bit, for a live view."""

    index: int = Field(description="frame index in the scan file")
    kind: str = Field(description="projection, flat or dark")
    width: int
    height: int
    scale: float = Field(description="picture pixels per detector pixel")
    pixels: str = Field(description="base64 of width x height bytes, row by row (1st to 99.5th percentile as 0 to 255)")
    bbs: list[Annotated[list[float], Field(min_length=2, max_length=2)]] | None = Field(
        None,
        description="BBs the live calibration found in this frame: [column, row] in detector pixels (none "
        "without calibrate: live)",
    )


@router.get(
    "/{scan_id}/frames/latest",
    response_model=FrameOut,
    summary="The newest frame of a running scan",
    responses={
        204: {"description": "no frame yet"},
        409: {"model": ErrorBody, "description": "the scan is not running"},
        **BENCH_UNAVAILABLE,
    },
)
async def latest_frame(scan_id: str, service: ServiceDep, _: Reader) -> Any:
    """A preview of the frame acquired last (the file has every frame at full depth)."""
    row = scan_or_404(service, scan_id)
    if service.rig.busy != scan_id:
        raise Conflict(
            f"scan {scan_id} is {row['state']}, not running",
            advice="its frames are in the scan file (GET /scans/{id}/file)",
        )
    frame = await _latest_frame(service, scan_id)
    return Response(status_code=204) if frame is None else FrameOut(**frame)


PREVIEW_MAX_AGE_S = 0.5  # every viewer of a running scan within this long gets the same preview: one bench request
_previews: dict[str, tuple[float, asyncio.Future[Any]]] = {}


async def _latest_frame(service: Any, scan_id: str) -> Any:
    now = time.monotonic()
    cached = _previews.get(scan_id)
    if cached is None or now - cached[0] > PREVIEW_MAX_AGE_S:
        _previews.clear()  # one scan runs at a time
        cached = _previews[scan_id] = (now, asyncio.ensure_future(service.rig.run("latest_frame", scan_id=scan_id)))
    return await asyncio.shield(cached[1])


@router.post(
    "/{scan_id}/abort",
    response_model=ScanOut,
    status_code=202,
    summary="Abort a running scan",
    responses={409: {"model": ErrorBody, "description": "the scan is not running"}, **BENCH_UNAVAILABLE, **DISK_FULL},
)
def abort_scan(scan_id: str, service: ServiceDep, _: ScanOperator, body: ScanAction | None = None) -> ScanOut:
    """Halt every axis, X-rays off, file marked aborted with the reason."""
    row = scan_or_404(service, scan_id)
    if service.rig.busy != scan_id:
        raise Conflict(f"scan {scan_id} is {row['state']}, not running", advice="there is nothing to abort")
    service.rig.abort(scan_id, (body or ScanAction()).reason)
    return _out(service, scan_or_404(service, scan_id))


@router.post(
    "/{scan_id}/pause",
    response_model=ScanOut,
    status_code=202,
    summary="Pause at the next frame",
    responses={409: {"model": ErrorBody, "description": "the scan is not running"}, **BENCH_UNAVAILABLE, **DISK_FULL},
)
def pause_scan(scan_id: str, service: ServiceDep, _: ScanOperator) -> ScanOut:
    """The current frame completes; X-rays stay off while paused."""
    scan_or_404(service, scan_id)
    service.rig.pause(scan_id)
    return _out(service, scan_or_404(service, scan_id))


@router.post(
    "/{scan_id}/resume",
    response_model=ScanOut,
    status_code=202,
    summary="Resume a paused scan",
    responses={409: {"model": ErrorBody, "description": "the scan is not running"}, **BENCH_UNAVAILABLE, **DISK_FULL},
)
def resume_scan(scan_id: str, service: ServiceDep, _: ScanOperator) -> ScanOut:
    """Continue from the next frame; refused while an emergency stop is latched or the scan is being aborted."""
    scan_or_404(service, scan_id)
    refused = service.estop.refusal("resuming a scan")
    if refused:
        raise StopLatched(refused)
    service.rig.resume(scan_id)
    return _out(service, scan_or_404(service, scan_id))


@router.get(
    "/{scan_id}/file",
    response_class=FileResponse,
    summary="Download the scan file (HDF5)",
    responses={
        200: {"content": {"application/x-hdf5": {}}},
        409: {"model": ErrorBody, "description": "still acquiring or being written by a job"},
    },
)
def download_scan(scan_id: str, service: ServiceDep, _: Reader) -> FileResponse:
    """The scan file (``scan-file.md``), once the scan has ended and no job writes to it."""
    path = ended_scan_file(service, scan_id, "download it")
    return FileResponse(path, media_type="application/x-hdf5", filename=f"{scan_id}.h5")
