"""``/pacs``: the DICOM nodes of the service's settings: find series, import C-arm runs as scans, send a
reconstruction as a CT series. Clients name a configured node; they never give an address."""

from __future__ import annotations

import tempfile
import uuid
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Query, Response
from pydantic import BaseModel, ConfigDict, Field

from orbitct.dicom import DicomSeriesOptions
from orbitct.scanfile.xa import AngleIncrements
from orbitct_app.pacs import PacsError, PacsNode, find_series, get_series, send
from orbitct_app.service.core.errors import (
    DISK_FULL,
    ERROR_RESPONSES,
    ErrorBody,
    Invalid,
    NotFound,
    Upstream,
)
from orbitct_app.service.core.files import summarize_scan
from orbitct_app.service.deps import Analyst, Reader, ServiceDep
from orbitct_app.service.routers.reconstructions import dicom_series

router = APIRouter(
    prefix="/pacs",
    tags=["pacs"],
    responses={
        **ERROR_RESPONSES,
        502: {"model": ErrorBody, "description": "the PACS node could not be reached or refused"},
    },
)
Uid = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[0-9]+(\.[0-9]+)*$")]


class NodeOut(BaseModel):
    """A DICOM node the service may talk to."""

    name: str
    ae_title: str
    host: str
    port: int


class SeriesOut(BaseModel):
    """One series a node holds (C-FIND at series level)."""

    study_uid: str
    series_uid: str
    modality: str
    description: str
    patient_id: str
    instances: str


class ImportRequest(BaseModel):
    """Fetch runs of one orbit (XA, in acquisition order) from a node and import them as a scan."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)
    study_uid: Uid
    series_uids: list[Uid] = Field(min_length=1, max_length=16, description="the runs, in acquisition order")
    name: str = Field(default="imported", min_length=1, max_length=100)
    angle_increments: AngleIncrements = Field(
        default="auto",
        description="how a classic run stores its per-frame angle increments: offsets from the first frame, steps "
        "from the previous frame, absolute angles, or auto (read from the values; the choice is among `assumed`)",
    )


class ImportOut(BaseModel):
    """The scan the runs became."""

    id: str
    frames: int
    assumed: list[str]


class SendRequest(DicomSeriesOptions):
    """Send a succeeded reconstruction to a node as a DICOM CT series (or one Enhanced CT object), written as
    :class:`orbitct.dicom.DicomSeriesOptions` say."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)
    reconstruction_id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")


class SendOut(BaseModel):
    """What the node stored."""

    node: str
    stored: int


def _node(service: Any, name: str) -> PacsNode:
    nodes = service.settings.pacs_nodes
    if name not in nodes:
        known = ", ".join(sorted(nodes)) or "none"
        raise NotFound(
            f"no PACS node {name!r} in the service settings",
            advice=f"use a configured node ({known}), or add it to the settings' pacs_nodes",
        )
    return PacsNode.parse(nodes[name])


@router.get("", response_model=list[NodeOut], summary="The configured DICOM nodes")
def list_nodes(service: ServiceDep, _: Reader) -> list[NodeOut]:
    """The nodes of ``pacs_nodes`` in the service settings."""
    out = []
    for name in sorted(service.settings.pacs_nodes):
        node = _node(service, name)
        out.append(NodeOut(name=name, ae_title=node.ae_title, host=node.host, port=node.port))
    return out


@router.get("/{node}/series", response_model=list[SeriesOut], summary="Find series on a node (C-FIND)")
def find(
    node: str,
    service: ServiceDep,
    _: Reader,
    modality: Annotated[str, Query(max_length=16, pattern=r"^[A-Z]*$")] = "",
    patient_id: Annotated[str, Query(max_length=64, pattern=r"^[\w .*?-]*$")] = "",
) -> list[SeriesOut]:
    """Series of the node matching the modality and patient id (both optional; DICOM wildcards allowed)."""
    target = _node(service, node)
    try:
        found = find_series(target, service.settings.pacs_calling_aet, Modality=modality, PatientID=patient_id)
    except PacsError as exc:
        raise Upstream(str(exc)) from None
    return [
        SeriesOut(
            study_uid=f["StudyInstanceUID"],
            series_uid=f["SeriesInstanceUID"],
            modality=f["Modality"],
            description=f["SeriesDescription"],
            patient_id=f["PatientID"],
            instances=f["NumberOfSeriesRelatedInstances"],
        )
        for f in found
    ]


@router.post(
    "/{node}/import",
    response_model=ImportOut,
    status_code=201,
    summary="Import runs from a node as a scan",
    responses=DISK_FULL,
)
def import_runs(node: str, body: ImportRequest, service: ServiceDep, who: Analyst, response: Response) -> ImportOut:
    """C-GET each run, then import them in the order given (``orbitct import dicom``): a complete scan with the
    nominal geometry from the runs' positioner angles and distances, ready to calibrate and reconstruct."""
    from orbitct.scanfile import ScanFile, ScanFileError
    from orbitct.scanfile.xa import import_xa

    target = _node(service, node)
    scan_id = uuid.uuid4().hex[:16]
    rel = f"scans/{scan_id}.h5"
    path = service.settings.data_dir / rel
    with tempfile.TemporaryDirectory(dir=service.settings.data_dir) as tmp:
        files: list[Path] = []
        try:
            for k, series in enumerate(body.series_uids):
                files += sorted(
                    get_series(target, body.study_uid, series, Path(tmp) / f"run{k}", service.settings.pacs_calling_aet)
                )
        except PacsError as exc:
            raise Upstream(str(exc)) from None
        try:
            import_xa(files, path, angle_increments=body.angle_increments)
            with ScanFile(path) as sf:
                frames = int(sf.count_by_kind()["projection"])
                assumed = list(sf.attrs_json("provenance", "import_assumptions_json")["assumed"])
        except ScanFileError as exc:
            path.unlink(missing_ok=True)
            raise Invalid(str(exc).replace(str(Path(tmp)), "<fetched runs>")) from None
    service.store.add_scan(
        scan_id,
        name=body.name,
        orbit="imported",
        owner=who.name,
        file=rel,
        frames_total=frames,
        request={"imported_from": {"node": node, "study_uid": body.study_uid, "series_uids": body.series_uids}},
    )
    service.store.update_scan(scan_id, state="complete", frames_done=frames, summary=summarize_scan(path))
    response.headers["Location"] = f"/scans/{scan_id}"
    return ImportOut(id=scan_id, frames=frames, assumed=assumed)


@router.post("/{node}/store", response_model=SendOut, summary="Send a reconstruction to a node (C-STORE)")
def store(node: str, body: SendRequest, service: ServiceDep, _: Analyst) -> SendOut:
    """The reconstruction as a DICOM CT series in Hounsfield units (as ``GET /reconstructions/{id}/dicom``),
    stored on the node."""
    target = _node(service, node)
    with tempfile.TemporaryDirectory(dir=service.settings.data_dir) as tmp:
        options = DicomSeriesOptions.model_validate(body.model_dump(exclude={"reconstruction_id"}))
        files = dicom_series(service, body.reconstruction_id, Path(tmp) / "series", options)
        try:
            stored = send(files, target, service.settings.pacs_calling_aet)
        except PacsError as exc:
            raise Upstream(str(exc)) from None
    return SendOut(node=node, stored=stored)
