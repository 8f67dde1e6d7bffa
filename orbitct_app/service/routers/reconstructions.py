"""``/reconstructions``: FDK or PWLS jobs on a scan; results as slices (PNG) and volumes (NIfTI, NumPy)."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Query, Response
from fastapi.responses import FileResponse
from pydantic import ConfigDict

from orbitct.dicom import DicomSeriesOptions
from orbitct_app.service.core.errors import (
    DISK_FULL,
    ERROR_RESPONSES,
    NOT_SUCCEEDED,
    Conflict,
    ErrorBody,
    FailedCheck,
    NotFound,
)
from orbitct_app.service.core.files import confined
from orbitct_app.service.deps import Analyst, Reader, ServiceDep
from orbitct_app.service.routers.calibrations import ScanId, check_scan_ready, submit
from orbitct_app.service.schemas import JobOut, job_or_404, job_out
from recon.options import ReconstructionOptions

router = APIRouter(prefix="/reconstructions", tags=["reconstructions"], responses=ERROR_RESPONSES)


class ReconstructionRequest(ReconstructionOptions):
    """Reconstruct a complete scan: the scan, and the options ``orbitct reconstruct`` and Python take.

    Without ``max_minutes`` the service's ``reconstruction_max_minutes`` applies: a job estimated to take longer
    fails at once, before any work."""

    model_config = ConfigDict(
        strict=True,
        json_schema_extra={
            "examples": [
                {
                    "scan_id": "a1b2c3d4e5f60718",
                    "algorithm": "pwls",
                    "geometry": "calibrated",
                    "shape": [64, 64, 64],
                    "iterations": 20,
                }
            ]
        },
    )

    scan_id: ScanId


def _file_facts(service: Any, scan: dict[str, Any]) -> tuple[list[str], list[str]]:
    """Geometries and reconstruction names the scan file holds now (the file is the truth; the record is a
    summary that a kill may have left behind)."""
    from orbitct.scanfile import ScanFile

    try:
        with ScanFile(service.settings.data_dir / scan["file"]) as sf:
            return [g for g in ("nominal", "calibrated", "truth") if sf.has_geometry(g)], sf.recon_names()
    except Exception:  # noqa: BLE001 - a job writing it right now: its record is the best there is
        return list(scan["summary"].get("geometries", [])), list(scan["summary"].get("recon", []))


def _failed_calibration(service: Any, scan: dict[str, Any]) -> list[str] | None:
    """Why the scan file's calibrated geometry failed its quality check; None when it passed, or when a calibration
    queued or running will replace it (that job's result decides, in the worker)."""
    from orbitct.scanfile import ScanFile
    from recon.pipeline import failed_geometry_reasons

    jobs = service.store.list_jobs(kind="calibration", scan_id=scan["id"], limit=500)
    if any(j["state"] in ("queued", "running") for j in jobs):
        return None
    try:
        with ScanFile(service.settings.data_dir / scan["file"]) as sf:
            return failed_geometry_reasons(sf, "calibrated")
    except Exception:  # noqa: BLE001 - a file being written: the job checks again when it runs
        return None


def _has_geometry(service: Any, scan: dict[str, Any], name: str, in_file: list[str]) -> bool:
    if name in in_file:
        return True
    if name == "calibrated":  # a calibration queued or running ahead of this job will write it
        jobs = service.store.list_jobs(kind="calibration", scan_id=scan["id"], limit=500)
        return any(j["state"] in ("queued", "running") for j in jobs)
    return False


@router.post(
    "",
    response_model=JobOut,
    status_code=202,
    summary="Start a reconstruction job",
    responses={
        409: {
            "model": ErrorBody,
            "description": "the scan is not complete, lacks the requested geometry, already has a "
            "reconstruction of that name (without overwrite), or (`failed_quality_check`) its calibrated geometry "
            'failed its quality check and `"accept_failed_geometry": true` was not sent',
        },
        **DISK_FULL,
    },
)
def start_reconstruction(body: ReconstructionRequest, service: ServiceDep, who: Analyst, response: Response) -> JobOut:
    """Queue a reconstruction; progress (iteration, cost) on ``/jobs/{id}/events``."""
    scan = check_scan_ready(service, body.scan_id)
    geometries, recons = _file_facts(service, scan)
    if not _has_geometry(service, scan, body.geometry, geometries):
        advice = (
            "calibrate it first (POST /calibrations)" if body.geometry == "calibrated" else "choose another geometry"
        )
        raise Conflict(f"scan {body.scan_id} has no {body.geometry} geometry", advice=advice)
    if body.geometry == "calibrated" and not body.accept_failed_geometry:
        reasons = _failed_calibration(service, scan)
        if reasons is not None:
            from recon import FailedGeometryError

            refused = FailedGeometryError(f"scan {body.scan_id}", reasons)
            raise FailedCheck(refused.what, advice=refused.advice('send "accept_failed_geometry": true'))
    name = body.recon_name
    if name in recons and not body.overwrite:
        raise Conflict(
            f"scan {body.scan_id} already has a reconstruction named {name!r}",
            advice='send "overwrite": true to replace it, or another "name"',
        )
    if body.max_minutes is None:
        body = body.model_copy(update={"max_minutes": service.settings.reconstruction_max_minutes})
    return submit(service, "reconstruction", body, who.name, response)


@router.get("", response_model=list[JobOut], summary="List reconstruction jobs")
def list_reconstructions(
    service: ServiceDep,
    _: Reader,
    scan_id: Annotated[str | None, Query(max_length=64)] = None,
    limit: Annotated[int, Query(ge=1, le=500)] = 100,
) -> list[JobOut]:
    """Reconstruction jobs, newest first."""
    return [job_out(j) for j in service.store.list_jobs(kind="reconstruction", scan_id=scan_id, limit=limit)]


@router.get("/{job_id}", response_model=JobOut, summary="A reconstruction job and its result summary")
def get_reconstruction(job_id: str, service: ServiceDep, _: Reader) -> JobOut:
    """State, progress (iteration, cost) and, once done, shape, voxel size and cost history."""
    return job_out(job_or_404(service, job_id, "reconstruction"))


def reconstruction_volume(service: Any, job_id: str) -> np.ndarray:
    """A succeeded reconstruction's volume (nz, ny, nx; 1/mm), memory-mapped; 404 or 409 otherwise."""
    job = job_or_404(service, job_id, "reconstruction")
    if job["state"] != "succeeded":
        raise Conflict(
            f"reconstruction {job_id} is {job['state']}", advice="ask again once it has succeeded (GET /jobs/{id})"
        )
    return np.load(confined(service.jobs.job_dir(job_id), "volume.npy"), mmap_mode="r")


@router.get(
    "/{job_id}/slices/{axis}",
    summary="One slice as PNG",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}, **NOT_SUCCEEDED},
)
def get_slice(
    job_id: str,
    axis: Literal["axial", "coronal", "sagittal"],
    service: ServiceDep,
    _: Reader,
    index: Annotated[int | None, Query(ge=0, le=4096, description="slice index (default: the middle)")] = None,
    grid_of: Annotated[
        str | None,
        Query(
            max_length=64,
            description="another succeeded reconstruction's id: this volume resampled onto that one's grid and "
            "shown in that one's grey window, so that the two slices compare side by side",
        ),
    ] = None,
) -> Response:
    """Axial (z), coronal (y) or sagittal (x) slice with axes in millimetres and a scale bar; grey levels from
    the volume's 1st to 99.5th percentile, of the voxels below 0.1/mm when metal is present (the title says so)."""
    from recon.export import display_window, slice_png

    vol = reconstruction_volume(service, job_id)
    job = job_or_404(service, job_id, "reconstruction")
    title = f"{job['result'].get('name', job_id)}: "
    if grid_of is not None and grid_of != job_id:
        other = reconstruction_volume(service, grid_of)
        other_job = job_or_404(service, grid_of, "reconstruction")
        window = display_window(np.asarray(other, dtype=np.float32))
        vol = np.load(_compare_file(service, job_id, grid_of, "npy"), mmap_mode="r")
        grid = _grid_of(other_job, other.shape)
        title = f"{job['result'].get('name', job_id)} on {other_job['result'].get('name', grid_of)}'s grid: "
    else:
        window, grid = None, _grid_of(job, vol.shape)
    dim = {"axial": 0, "coronal": 1, "sagittal": 2}[axis]
    n = vol.shape[dim]
    i = n // 2 if index is None else index
    if i >= n:
        raise NotFound(f"no {axis} slice {i} in this volume", advice=f"ask for one of its {axis} slices 0..{n - 1}")
    png = slice_png(np.asarray(vol, dtype=np.float32), grid, axis, i, title=title, window=window)
    return Response(png, media_type="image/png")


@router.get(
    "/{job_id}/volume",
    response_class=FileResponse,
    summary="Download the volume",
    responses={
        200: {"content": {"application/octet-stream": {}}},
        409: {"model": ErrorBody, "description": "the job has not succeeded, or has no export in that format"},
    },
)
def get_volume(
    job_id: str,
    service: ServiceDep,
    _: Reader,
    format: Literal["nifti", "npy"] = "nifti",
    grid_of: Annotated[
        str | None,
        Query(
            max_length=64,
            description="another succeeded reconstruction's id: this volume resampled onto that one's grid "
            "(trilinear, 0 outside), so that the two compare voxel for voxel",
        ),
    ] = None,
) -> FileResponse:
    """The volume as NIfTI (``.nii.gz``, millimetres) or a NumPy float32 array (z, y, x), on its own grid or on
    another reconstruction's (``grid_of``)."""
    reconstruction_volume(service, job_id)
    folder = service.jobs.job_dir(job_id)
    if grid_of is not None and grid_of != job_id:
        return _on_grid_of(service, job_id, grid_of, format)
    if format == "npy":
        return FileResponse(confined(folder, "volume.npy"), filename=f"{job_id}.npy")
    names = [p.name for p in folder.iterdir() if p.name.endswith((".nii", ".nii.gz"))]
    if not names:
        raise Conflict("this reconstruction has no NIfTI export", advice="download it as NumPy instead (?format=npy)")
    return FileResponse(confined(folder, sorted(names)[0]), filename=sorted(names)[0])


def _grid_of(job: dict[str, Any], shape: tuple[int, ...]) -> Any:
    """The grid of a succeeded reconstruction ``job`` whose volume has ``shape``."""
    from orbitct.geometry import VolumeGrid

    nz, ny, nx = shape
    return VolumeGrid((nz, ny, nx), tuple(job["result"]["voxel_mm"]), tuple(job["result"]["origin_mm"]))


def _on_grid_of(service: Any, job_id: str, other_id: str, format: str) -> FileResponse:
    """``job_id``'s volume resampled onto ``other_id``'s grid, as a download."""
    path = _compare_file(service, job_id, other_id, format)
    return FileResponse(path, filename=f"{job_id}-{path.name}")


def _compare_file(service: Any, job_id: str, other_id: str, format: str) -> Path:
    """The file of ``job_id``'s volume resampled onto ``other_id``'s grid, made once and kept in the job's folder."""
    from recon.export import export_nifti
    from recon.resample import resample_volume

    other = reconstruction_volume(service, other_id)  # a known job's id: a plain name
    name = f"on-grid-of-{other_id}." + ("npy" if format == "npy" else "nii.gz")
    path: Path = service.jobs.job_dir(job_id) / "compare" / name  # apart from the exported files
    if not path.is_file():
        path.parent.mkdir(exist_ok=True)
        vol = reconstruction_volume(service, job_id)
        job, onto = job_or_404(service, job_id), _grid_of(job_or_404(service, other_id), other.shape)
        resampled = resample_volume(vol, _grid_of(job, vol.shape), onto)
        part = path.with_name(f"part-{uuid.uuid4().hex[:8]}-{name}")  # nibabel compresses by the name's end
        if format == "npy":
            np.save(part, resampled)
        else:
            export_nifti(resampled, onto, part)
        part.replace(path)  # complete or absent: a second request never reads half a file
    return path


@router.get(
    "/{job_id}/dicom",
    response_class=FileResponse,
    summary="The volume as a DICOM CT series or one Enhanced CT object (zip)",
    responses={200: {"content": {"application/zip": {}}}, **NOT_SUCCEEDED},
)
def get_dicom(
    job_id: str,
    service: ServiceDep,
    _: Reader,
    options: Annotated[DicomSeriesOptions, Query()],
) -> FileResponse:
    """One CT image per axial slice (or one multi-frame Enhanced CT object) in Hounsfield units, the object frame as
    the patient frame, fresh UIDs, the algorithm and geometry in the series description; zipped (written once per
    water value)."""
    import hashlib
    import tempfile
    import zipfile

    reconstruction_volume(service, job_id)  # 404 or 409 before anything is written
    folder = service.jobs.job_dir(job_id)
    asked = hashlib.sha256(options.model_dump_json().encode()).hexdigest()[:16]
    name = f"dicom-{job_id}-{asked}.zip"  # written once per set of options
    target = folder / name
    if not target.exists():
        with tempfile.TemporaryDirectory(dir=folder) as tmp:
            files = dicom_series(service, job_id, Path(tmp) / "series", options)
            partial = Path(tmp) / "series.zip"
            with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as zf:
                for f in files:
                    zf.write(f, f"{job_id}/{f.name}")
            partial.replace(target)
    return FileResponse(confined(folder, name), media_type="application/zip", filename=f"{job_id}-dicom.zip")


ENHANCED_CT_NAME = "CT_ENHANCED.dcm"


def dicom_series(service: Any, job_id: str, out_dir: Path, options: DicomSeriesOptions) -> list[Path]:
    """Write a succeeded reconstruction as a DICOM CT series (or one Enhanced CT object) into ``out_dir``; the
    files."""
    from orbitct.geometry import VolumeGrid
    from orbitct.scanfile.xa import patient_sides_caveat
    from recon.dicom import SeriesInfo, export_dicom_ct, export_enhanced_ct

    vol = reconstruction_volume(service, job_id)
    job = job_or_404(service, job_id, "reconstruction")
    result, params = job["result"], job["params"]
    grid = VolumeGrid(tuple(vol.shape), tuple(result["voxel_mm"]), tuple(result["origin_mm"]))
    info = SeriesInfo.from_options(
        options,
        description=f"orbitct {result.get('name', job_id)}: {params.get('algorithm', '?').upper()} "
        f"{params.get('geometry', '?')} geometry",
        patient_id=job["scan_id"],
        comments=patient_sides_caveat(
            ((service.store.get_scan(job["scan_id"]) or {}).get("summary") or {}).get("import_assumptions", [])
        ),
    )
    if options.enhanced:
        return [export_enhanced_ct(np.asarray(vol, dtype=np.float32), grid, out_dir / ENHANCED_CT_NAME, info)]
    return export_dicom_ct(np.asarray(vol, dtype=np.float32), grid, out_dir, info)


@router.get("/{job_id}/files", response_model=list[str], summary="Result files", responses=NOT_SUCCEEDED)
def list_files(job_id: str, service: ServiceDep, _: Reader) -> list[str]:
    """Names of the exported files (slices, NIfTI)."""
    reconstruction_volume(service, job_id)
    return sorted(p.name for p in service.jobs.job_dir(job_id).iterdir() if p.is_file())


@router.get("/{job_id}/files/{name}", response_class=FileResponse, summary="One result file", responses=NOT_SUCCEEDED)
def get_file(job_id: str, name: str, service: ServiceDep, _: Reader) -> FileResponse:
    """An exported file by name (from ``/files``)."""
    reconstruction_volume(service, job_id)
    return FileResponse(confined(service.jobs.job_dir(job_id), name))
