"""A scan's per-view geometry for another reconstruction toolkit (``orbitct export <toolkit>`` over REST)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from orbitct.toolkits import GeometryExportOptions
from orbitct_app.service.core.errors import ERROR_RESPONSES, Conflict, ErrorBody, FailedCheck, NotFound
from orbitct_app.service.deps import Reader, ServiceDep
from orbitct_app.service.schemas import ended_scan_file

router = APIRouter(prefix="/scans", tags=["geometry"], responses=ERROR_RESPONSES)


@router.get(
    "/{scan_id}/geometry/export",
    summary="The scan's per-view geometry for another toolkit (ASTRA, tomosipo, LEAP, diffct, TIGRE, CIL, RTK)",
    responses={
        200: {"content": {"application/json": {}, "application/xml": {}}},
        404: {"model": ErrorBody, "description": "no such scan, or it has not the geometry asked for"},
        409: {
            "model": ErrorBody,
            "description": "still acquiring or written by a job, a failed calibrated geometry, or views without one",
        },
    },
)
def export_geometry(
    scan_id: str, service: ServiceDep, _: Reader, options: Annotated[GeometryExportOptions, Query()]
) -> Response:
    """The document ``orbitct export <toolkit>`` writes: the toolkit call it feeds and its arguments in the
    toolkit's conventions (JSON; RTK: its geometry XML), as an attachment. When the toolkit cannot hold the
    geometry exactly, ``X-Orbitct-Warning`` says how far a projected point lands from orbitct's projection."""
    from orbitct.scanfile import ScanFileError
    from recon.errors import FailedGeometryError, ReconError
    from recon.geometry_export import export_scan_geometry

    path = ended_scan_file(service, scan_id, "export its geometry")
    try:
        export = export_scan_geometry(path, options, name=f"scan {scan_id}")
    except FailedGeometryError as exc:
        raise FailedCheck(exc.what, advice=exc.advice("add accept_failed_geometry=true")) from None
    except ScanFileError:  # its sentence names the file on the server: said here in the API's terms
        raise NotFound(
            f"scan {scan_id} has no {options.geometry} geometry",
            advice="calibrate the scan first, or ask for geometry=nominal (the orbit's own)",
        ) from None
    except ReconError as exc:
        raise Conflict(str(exc)) from None
    headers = {"Content-Disposition": f'attachment; filename="{scan_id}-{export.toolkit}{export.suffix}"'}
    if export.warning is not None:
        headers["X-Orbitct-Warning"] = export.warning
    return Response(export.text, media_type=export.media_type, headers=headers)
