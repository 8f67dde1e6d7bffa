"""``/plans/bbs``: where to tape the BBs for one of the experiments' objects and an orbit, as ``orbitct plan bbs``
makes it; each plan is kept (its JSON, which ``orbitct simulate --bbs-from`` reads, and its picture)."""

from __future__ import annotations

import json
import uuid
from typing import Any, Literal

from fastapi import APIRouter, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator

from orbitct_app.bbplan import (
    MAX_BBS,
    BBPlanError,
    BBPlanRequest,
    make_bb_plan,
    outline_from_volume,
    write_bb_plan,
)
from orbitct_app.service.core.errors import ERROR_RESPONSES, Invalid, NotFound
from orbitct_app.service.core.files import confined
from orbitct_app.service.deps import Analyst, Reader, ServiceDep
from orbitct_app.service.routers.reconstructions import reconstruction_volume
from orbitct_app.service.routers.surfaces import load_kept_surface
from orbitct_app.service.schemas import job_or_404

router = APIRouter(prefix="/plans/bbs", tags=["plans"], responses=ERROR_RESPONSES)


class KeepOutIn(BaseModel):
    """A patch of the object's surface without BBs: polar angles (deg, counterclockwise from +x; through 0 when
    ``angle_to_deg < angle_from_deg``; 0 to 360: the whole turn) between two heights (mm)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    angle_from_deg: float = Field(ge=0.0, lt=360.0)
    angle_to_deg: float = Field(ge=0.0, le=360.0)
    z_min_mm: float = Field(ge=-1000.0, le=1000.0)
    z_max_mm: float = Field(ge=-1000.0, le=1000.0)

    @model_validator(mode="after")
    def _heights(self) -> "KeepOutIn":
        if not self.z_min_mm < self.z_max_mm:
            raise ValueError(f"z_min_mm ({self.z_min_mm:g}) must be below z_max_mm ({self.z_max_mm:g})")
        if self.angle_from_deg == self.angle_to_deg % 360.0 and self.angle_to_deg - self.angle_from_deg != 360.0:
            raise ValueError(f"angle_from_deg and angle_to_deg ({self.angle_from_deg:g}) make no patch; the whole turn is "
                             "0 to 360")
        return self


class BBPlanIn(BaseModel):
    """What to plan: the object and default orbit of an experiment, the orbit, the panel, how many BBs (or the
    accuracy to reach with as few as possible), where not to put them, and the detection's centroid noise."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, json_schema_extra={"examples": [
        {"experiment": "A", "frames": 500, "bbs": 8, "keep_out": [
            {"angle_from_deg": 300, "angle_to_deg": 60, "z_min_mm": -20, "z_max_mm": 10}]}]})

    experiment: Literal["A", "B", "C"]
    orbit: str | None = Field(default=None, max_length=40, pattern=r"^[a-z_-]+$")
    frames: int | None = Field(default=None, ge=2, le=5000)
    bbs: int = Field(default=8, ge=4, le=MAX_BBS)
    target_px: float | None = Field(default=None, gt=0.0, le=10.0,
                                    description="plan the fewest BBs whose every view is predicted within this (px)")
    max_bbs: int = Field(default=20, ge=4, le=MAX_BBS)
    keep_out: list[KeepOutIn] = Field(default_factory=list, max_length=20)
    detector_px: int = Field(default=768, ge=8, le=4096)
    noise_px: float = Field(default=0.1, gt=0.0, le=5.0)
    seed: int = Field(default=0, ge=0, le=2**31)
    surface_reconstruction_id: str | None = Field(
        default=None, min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$",
        description="plan on the object's real outer surface: a succeeded reconstruction of it (a prior volume)")
    surface_threshold_per_mm: float | None = Field(default=None, gt=0.0, le=10.0,
                                                   description="its object/air threshold (default: Otsu's)")
    surface_id: str | None = Field(default=None, pattern=r"^[0-9a-f]{12}$",
                                   description="plan on an uploaded surface mesh (POST /surfaces)")

    @model_validator(mode="after")
    def _one_surface(self) -> "BBPlanIn":
        if self.surface_id is not None and self.surface_reconstruction_id is not None:
            raise ValueError("give surface_id or surface_reconstruction_id, not both")
        return self


class BBPlanSummary(BaseModel):
    """A kept plan, listed."""

    id: str
    experiment: str
    orbit: str
    views: int
    bbs: int
    predicted_px_max: float | None
    under_determined: int


def _plans_dir(service: Any) -> Any:
    folder = service.settings.data_dir / "plans"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _summary(plan_id: str, body: dict[str, Any]) -> BBPlanSummary:
    return BBPlanSummary(id=plan_id, experiment=body["experiment"], orbit=body["orbit"], views=body["views"],
                         bbs=len(body["bbs"]), predicted_px_max=body["predicted"]["predicted_px_max"],
                         under_determined=body["predicted"]["under_determined"])


@router.post("", status_code=201, summary="Plan the BBs for an experiment's object and orbit")
def create_plan(body: BBPlanIn, service: ServiceDep, response: Response, _: Analyst) -> dict[str, Any]:
    """Search BB positions that minimise the predicted calibration error of the orbit's views (seconds; with
    ``target_px``, a minute or so); 201 with the plan (``Location: /plans/bbs/{id}``), the experiment's own
    placement beside it, and warnings for views left under-determined."""
    from calib.plan import KeepOut

    surface = None
    if body.surface_reconstruction_id is not None:
        job = job_or_404(service, body.surface_reconstruction_id, "reconstruction")
        volume = reconstruction_volume(service, body.surface_reconstruction_id)
        try:
            surface = outline_from_volume(volume, job["result"]["voxel_mm"], job["result"]["origin_mm"],
                                          body.surface_threshold_per_mm, f"reconstruction {job['id']}")
        except BBPlanError as exc:
            raise Invalid(str(exc)) from None
    elif body.surface_id is not None:
        try:
            surface = load_kept_surface(service, body.surface_id)
        except BBPlanError as exc:
            raise Invalid(str(exc)) from None
    request = BBPlanRequest(experiment=body.experiment, orbit=body.orbit, frames=body.frames, n_bbs=body.bbs,
                            detector_px=body.detector_px, noise_px=body.noise_px, seed=body.seed,
                            keep_out=tuple(KeepOut(**z.model_dump()) for z in body.keep_out), target_px=body.target_px,
                            max_bbs=body.max_bbs, surface=surface)
    try:
        plan = make_bb_plan(request)
    except BBPlanError as exc:
        raise Invalid(str(exc)) from None
    plan_id = uuid.uuid4().hex[:12]
    write_bb_plan(plan, _plans_dir(service) / f"{plan_id}.json")
    response.headers["Location"] = f"/plans/bbs/{plan_id}"
    return {"id": plan_id, **plan.body}


@router.get("", response_model=list[BBPlanSummary], summary="The kept plans, newest first")
def list_plans(service: ServiceDep, _: Reader) -> list[BBPlanSummary]:
    """Every kept plan with its experiment, orbit, BB count and worst predicted view."""
    files = sorted(_plans_dir(service).glob("*.json"), key=lambda p: p.stat().st_mtime, reverse=True)
    return [_summary(f.stem, json.loads(f.read_text())) for f in files]


def _plan_file(service: Any, plan_id: str, suffix: str) -> Any:
    path = confined(_plans_dir(service), f"{plan_id}{suffix}")
    if not path.exists():
        raise NotFound(f"no BB plan {plan_id!r}")
    return path


@router.get("/{plan_id}", summary="One plan (the JSON `orbitct simulate --bbs-from` reads)")
def get_plan(plan_id: str, service: ServiceDep, _: Reader) -> dict[str, Any]:
    """The plan as it was made: BBs (object frame, and angle/height on the object), predictions per view."""
    return {"id": plan_id, **json.loads(_plan_file(service, plan_id, ".json").read_text())}


@router.get("/{plan_id}/picture", response_class=FileResponse, summary="The plan's picture (PNG)",
            responses={200: {"content": {"image/png": {}}}})
def get_picture(plan_id: str, service: ServiceDep, _: Reader) -> FileResponse:
    """The BBs with their numbers on the unrolled surface (keep-out zones grey), and BBs and predicted error per
    view along the orbit."""
    return FileResponse(_plan_file(service, plan_id, ".png"), media_type="image/png")
