"""``/surfaces``: an object's outer surface uploaded as a mesh, kept for planning BBs on it (``POST /plans/bbs`` with
``surface_id``), as ``orbitct plan bbs --surface MESH`` does on the command line."""

from __future__ import annotations

import dataclasses
import json
import re
import uuid
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel

from orbitct_app.bbplan import MESH_SUFFIXES, BBPlanError, load_surface
from orbitct_app.service.core.errors import ERROR_RESPONSES, Invalid, NotFound
from orbitct_app.service.core.files import confined
from orbitct_app.service.deps import Analyst, Reader, ServiceDep

router = APIRouter(prefix="/surfaces", tags=["plans"], responses=ERROR_RESPONSES)
_NAME = r"^[A-Za-z0-9][A-Za-z0-9 _.()-]{0,99}$"


class SurfaceOut(BaseModel):
    """A kept surface: its id (for ``surface_id``), the uploaded file's name, and the outline made of it."""

    id: str
    name: str
    surface: dict[str, Any]


def _folder(service: Any) -> Path:
    folder = service.settings.data_dir / "surfaces"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def surface_file(service: Any, surface_id: str) -> tuple[Path, str]:
    """The kept mesh of ``surface_id`` and its uploaded name; 404 when there is none."""
    if not re.fullmatch(r"[0-9a-f]{12}", surface_id) or not (_folder(service) / f"{surface_id}.json").is_file():
        raise NotFound(f"no surface {surface_id[:60]!r}")
    name = json.loads(confined(_folder(service), f"{surface_id}.json").read_text())["name"]
    return confined(_folder(service), surface_id + Path(name).suffix.lower()), name


def load_kept_surface(service: Any, surface_id: str) -> Any:
    """The outline (``calib.surfaces.Outline``) of a kept mesh, named by its uploaded name."""
    path, name = surface_file(service, surface_id)
    return dataclasses.replace(load_surface(str(path)), source=name)


@router.post(
    "",
    status_code=201,
    response_model=SurfaceOut,
    summary="Upload an object's surface mesh",
    openapi_extra={
        "requestBody": {
            "required": True,
            "description": "the mesh file itself (its content is "
            "checked by the service: 422 when it is no mesh or holds no triangles)",
            "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary", "minLength": 1}}},
        }
    },
)
async def upload_surface(
    request: Request,
    service: ServiceDep,
    response: Response,
    _: Analyst,
    name: Annotated[
        str,
        Query(
            pattern=_NAME,
            description="the file's name, with its suffix: " + ", ".join(MESH_SUFFIXES) + " (422 otherwise)",
        ),
    ],
) -> SurfaceOut:
    """The mesh file is the request body (mm, in the object frame: z along the rotation axis, as the scan's
    reconstructions); it is read at once and refused in one line when it is no mesh or holds no triangles. 201 with
    the outline made of it (``Location: /surfaces/{id}``)."""
    suffix = Path(name).suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise Invalid(f"surface {name!r} is not a mesh file", advice=f"upload a {', '.join(MESH_SUFFIXES)} file")
    data = await request.body()
    if not data:
        raise Invalid("the request body is empty", advice="send the mesh file itself as the body")
    surface_id = uuid.uuid4().hex[:12]
    path = _folder(service) / f"{surface_id}{suffix}"
    path.write_bytes(data)
    try:
        outline = await run_in_threadpool(load_surface, str(path))
    except (BBPlanError, ValueError) as exc:
        path.unlink(missing_ok=True)
        raise Invalid(str(exc).replace(repr(str(path)), repr(name))) from None
    except Exception:  # noqa: BLE001 - a file the mesh reader cannot parse at all
        path.unlink(missing_ok=True)
        raise Invalid(
            f"surface {name!r} is not a readable mesh", advice=f"export it again as {', '.join(MESH_SUFFIXES)}"
        ) from None
    described = dataclasses.replace(outline, source=name).describe()
    (_folder(service) / f"{surface_id}.json").write_text(json.dumps({"name": name, "surface": described}))
    response.headers["Location"] = f"/surfaces/{surface_id}"
    return SurfaceOut(id=surface_id, name=name, surface=described)


@router.get("", response_model=list[SurfaceOut], summary="The kept surfaces, newest first")
def list_surfaces(service: ServiceDep, _: Reader) -> list[SurfaceOut]:
    """Every uploaded surface with its outline's heights and radii."""
    files = sorted(_folder(service).glob("*.json"), key=lambda p: p.stat().st_mtime, reverse=True)
    return [SurfaceOut(id=f.stem, **json.loads(f.read_text())) for f in files]


@router.get("/{surface_id}", response_model=SurfaceOut, summary="One kept surface")
def get_surface(surface_id: str, service: ServiceDep, _: Reader) -> SurfaceOut:
    """Its uploaded name and the outline made of it; 404 for an unknown id."""
    surface_file(service, surface_id)
    return SurfaceOut(id=surface_id, **json.loads(confined(_folder(service), f"{surface_id}.json").read_text()))
