"""``/plans/bbs``: where to tape the BBs for one of the experiments' objects and an orbit, as ``orbitct plan bbs``
makes it; each plan is kept (its JSON, which ``orbitct simulate --bbs-from`` reads, and its picture)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator

from orbitct_app.bbplan import (
    BBPlanError,
    BBPlanRequest,
    check_bb_plan_request,
    load_surface,
    outline_from_volume,
)
from orbitct_app.bbplan_options import BBPlanOptions
from orbitct_app.service.core.errors import (
    ERROR_RESPONSES,
    Conflict,
    ErrorBody,
    Invalid,
    NotFound,
)
from orbitct_app.service.core.schema_rules import at_most_one_of, schema_extra
from orbitct_app.service.deps import Analyst, Reader, ServiceDep
from orbitct_app.service.jobs.bbplans import PlanEnded, PlansBusy, plan_path
from orbitct_app.service.routers.reconstructions import reconstruction_volume
from orbitct_app.service.routers.surfaces import load_kept_surface
from orbitct_app.service.schemas import job_or_404

_PLAN_ID = re.compile(r"[0-9a-f]{12}")
router = APIRouter(prefix="/plans/bbs", tags=["plans"], responses=ERROR_RESPONSES)


class BBPlanIn(BBPlanOptions):
    """A plan (:class:`orbitct_app.bbplan_options.BBPlanOptions`) on the experiment's surface, an uploaded mesh, a
    reconstruction of the object or a shape."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        allow_inf_nan=False,
        json_schema_extra=schema_extra(
            [
                {
                    "experiment": "A",
                    "frames": 500,
                    "bbs": 8,
                    "keep_out": [{"angle_from_deg": 300, "angle_to_deg": 60, "z_min_mm": -20, "z_max_mm": 10}],
                }
            ],
            at_most_one_of("surface_id", "surface_reconstruction_id", "surface_shape"),
        ),
    )

    surface_reconstruction_id: str | None = Field(
        default=None,
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_-]+$",
        description="plan on the object's real outer surface: a succeeded reconstruction of it (a prior volume)",
    )
    surface_id: str | None = Field(
        default=None, pattern=r"^[0-9a-f]{12}$", description="plan on an uploaded surface mesh (POST /surfaces)"
    )
    surface_shape: str | None = Field(
        default=None,
        max_length=80,
        pattern=r"^(cylinder|ellipsoid):[-+0-9.eE,:]+$",
        description="plan on a shape by parameters (mm): cylinder:R,ZMIN:ZMAX, "
        "cylinder:A,B,ZMIN:ZMAX or ellipsoid:A,B,C[,ZMIN:ZMAX]",
    )

    @model_validator(mode="after")
    def _one_surface(self) -> BBPlanIn:
        given = [
            k for k in ("surface_id", "surface_reconstruction_id", "surface_shape") if getattr(self, k) is not None
        ]
        if len(given) > 1:
            raise ValueError(
                f"give one of surface_id, surface_reconstruction_id and surface_shape, not {' and '.join(given)}"
            )
        return self


class BBPlanSummary(BaseModel):
    """A plan, listed: once done, its BB count and worst predicted view; while it is made or when it failed, its
    state and why."""

    id: str
    state: Literal["planning", "done", "failed", "cancelled"]
    experiment: str
    orbit: str
    views: int
    bbs: int | None
    predicted_px_max: float | None
    under_determined: int | None
    created: str | None = None
    reason: str | None = None


class PlanStateOut(BaseModel):
    """A plan not (or not yet) made: ``planning`` (poll ``GET /plans/bbs/{id}``), ``failed`` or ``cancelled``."""

    id: str
    state: Literal["planning", "failed", "cancelled"]
    owner: str
    created: str
    experiment: str
    orbit: str
    views: int
    bbs: int | None = None
    target_px: float | None = None
    ended: str | None = None
    reason: str | None = None
    progress: dict[str, Any] | None = Field(
        None, description="how far the plan got: stage (prepare, count, plan), done, total, message"
    )
    expected_s: float | None = Field(
        None, description="how long the plan is expected to take in all, measured on this machine once it started"
    )


def _summary(plan_id: str, body: dict[str, Any]) -> BBPlanSummary:
    return BBPlanSummary(
        id=plan_id,
        state="done",
        experiment=body["experiment"],
        orbit=body["orbit"],
        views=body["views"],
        bbs=len(body["bbs"]),
        predicted_px_max=body["predicted"]["predicted_px_max"],
        under_determined=body["predicted"]["under_determined"],
    )


@router.post(
    "",
    status_code=202,
    response_model=PlanStateOut,
    summary="Plan the BBs for an experiment's object and orbit",
    responses={409: {"model": ErrorBody, "description": "as many plans as allowed are already waiting"}},
)
def create_plan(body: BBPlanIn, service: ServiceDep, response: Response, who: Analyst) -> PlanStateOut:
    """Check the request and queue the plan (202, ``Location: /plans/bbs/{id}``): plans are made one at a time in
    the background (seconds; with ``target_px``, minutes). Poll ``GET /plans/bbs/{id}`` until its ``state`` is
    ``done`` (the plan, the experiment's own placement beside it, warnings for views left under-determined),
    ``failed`` (with the reason) or ``cancelled``."""

    surface = None
    if body.surface_reconstruction_id is not None:
        job = job_or_404(service, body.surface_reconstruction_id, "reconstruction")
        volume = reconstruction_volume(service, body.surface_reconstruction_id)
        try:
            surface = outline_from_volume(
                volume,
                job["result"]["voxel_mm"],
                job["result"]["origin_mm"],
                body.surface_threshold_per_mm,
                f"reconstruction {job['id']}",
            )
        except BBPlanError as exc:
            raise Invalid(str(exc)) from None
    elif body.surface_id is not None:
        try:
            surface = load_kept_surface(service, body.surface_id)
        except BBPlanError as exc:
            raise Invalid(str(exc)) from None
    elif body.surface_shape is not None:
        try:
            surface = load_surface(body.surface_shape)
        except BBPlanError as exc:
            raise Invalid(str(exc)) from None
    request = BBPlanRequest.from_options(body, surface)
    try:
        asked = check_bb_plan_request(request)
    except BBPlanError as exc:
        raise Invalid(str(exc)) from None
    asked |= {"bbs": None, "target_px": body.target_px} if body.target_px is not None else {"bbs": body.bbs}
    try:
        state = service.plans.submit(request, who.name, asked)
    except PlansBusy as exc:
        raise Conflict(str(exc)) from None
    response.headers["Location"] = f"/plans/bbs/{state['id']}"
    return PlanStateOut(**state)


@router.get("", response_model=list[BBPlanSummary], summary="The plans, newest first")
def list_plans(service: ServiceDep, _: Reader) -> list[BBPlanSummary]:
    """Every plan: those done with their experiment, orbit, BB count and worst predicted view; those waiting, being
    made, failed or cancelled with their state."""
    folder = service.plans.folder
    listed = [
        (f.stat().st_mtime, _summary(f.stem, json.loads(f.read_text())))
        for f in folder.glob("*.json")
        if _PLAN_ID.fullmatch(f.stem)
    ]
    done = {s.id for _, s in listed}
    for changed, state in service.plans.states():
        if state["id"] not in done:
            fields = {k: v for k, v in state.items() if k in BBPlanSummary.model_fields}
            listed.append((changed, BBPlanSummary(predicted_px_max=None, under_determined=None, **fields)))
    return [s for _, s in sorted(listed, key=lambda x: x[0], reverse=True)]


def _plan_or_state(service: Any, plan_id: str) -> Path | dict[str, Any]:
    """The done plan's JSON file, or else its state record (waiting, being made, failed, cancelled); 404 when
    neither."""
    if _PLAN_ID.fullmatch(plan_id):
        path = plan_path(service.plans.folder, plan_id)
        if path.is_file():
            return path
        state: dict[str, Any] | None = service.plans.state(plan_id)
        if state is not None:
            return state
    raise NotFound(f"no BB plan {plan_id!r}")


@router.get("/{plan_id}", summary="One plan (the JSON `orbitct simulate --bbs-from` reads), or its state")
def get_plan(plan_id: str, service: ServiceDep, _: Reader) -> dict[str, Any]:
    """The plan as it was made (``state`` done): BBs (object frame, and angle/height on the object), predictions
    per view; while it is made, or when it failed or was cancelled, its state record (``reason``)."""
    found = _plan_or_state(service, plan_id)
    return found if isinstance(found, dict) else {"id": plan_id, "state": "done", **json.loads(found.read_text())}


@router.get(
    "/{plan_id}/picture",
    response_class=FileResponse,
    summary="The plan's picture (PNG)",
    responses={200: {"content": {"image/png": {}}}, 409: {"model": ErrorBody, "description": "not made (yet)"}},
)
def get_picture(plan_id: str, service: ServiceDep, _: Reader) -> FileResponse:
    """The object with the numbered BBs, the BBs on the unrolled surface (keep-out zones grey), and BBs and
    predicted error per view along the orbit."""
    found = _plan_or_state(service, plan_id)
    if isinstance(found, dict):
        reason = f": {found['reason']}" if found.get("reason") else ""
        raise Conflict(
            f"plan {plan_id} is {found['state']}{reason}",
            advice="its picture exists once it is done (GET /plans/bbs/{id})",
        )
    return FileResponse(found.with_suffix(".png"), media_type="image/png")


@router.post(
    "/{plan_id}/cancel",
    status_code=202,
    response_model=PlanStateOut,
    summary="Cancel a plan",
    responses={409: {"model": ErrorBody, "description": "the plan has already ended"}},
)
def cancel_plan(plan_id: str, service: ServiceDep, who: Analyst) -> PlanStateOut:
    """Stop a plan waiting or being made; it ends ``cancelled``."""
    if isinstance(_plan_or_state(service, plan_id), Path):
        raise Conflict(f"plan {plan_id} is already done", advice="there is nothing to cancel")
    try:
        service.plans.cancel(plan_id, who.name)
    except PlanEnded as exc:
        raise Conflict(str(exc), advice="there is nothing to cancel") from None
    state = service.plans.state(plan_id)
    if state is None:  # done meanwhile
        raise Conflict(f"plan {plan_id} is already done", advice="there is nothing to cancel")
    return PlanStateOut(**state)
