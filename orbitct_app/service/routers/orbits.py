"""``/orbits``: orbit kinds with their parameter schemas, validation, and a PNG preview."""

from __future__ import annotations

import io
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from fastapi import APIRouter, Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from orbitct.orbits import ORBIT_KINDS, OrbitError, make_orbit
from orbitct_app.service.core.errors import (
    ERROR_RESPONSES,
    FieldProblem,
    Invalid,
    NotFound,
    validation_details,
)
from orbitct_app.service.deps import Reader

router = APIRouter(prefix="/orbits", tags=["orbits"], responses=ERROR_RESPONSES)
if TYPE_CHECKING:
    OrbitKind = str
else:
    OrbitKind = Literal[tuple(ORBIT_KINDS)]  # the registered kinds, checked by the request models
PREVIEW_MAX_FRAMES = 20_000


class OrbitKindOut(BaseModel):
    """One orbit kind: what it is and the JSON schema of its parameters (degrees)."""

    kind: str
    description: str
    parameters: dict[str, Any]


class OrbitSpec(BaseModel):
    """An orbit kind and its parameters."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        allow_inf_nan=False,
        json_schema_extra={
            "examples": [{"kind": "sawtooth", "params": {"n_frames": 500, "amplitude_deg": 20, "cycles": 2}}]
        },
    )

    kind: OrbitKind
    params: dict[str, Any] = Field(default_factory=dict)


class OrbitSummary(BaseModel):
    """A valid orbit: normalised parameters and the ranges it covers."""

    kind: str
    params: dict[str, Any]
    n_frames: int
    n_segments: int
    rotation_deg: list[float] = Field(min_length=2, max_length=2, description="smallest and largest rotation")
    tilt_deg: list[float] = Field(min_length=2, max_length=2, description="smallest and largest tilt")
    step_deg: list[float] = Field(min_length=2, max_length=2, description="mean step per frame: rotation, tilt")


def _describe(kind: str) -> OrbitKindOut:
    model = ORBIT_KINDS[kind]
    schema = model.model_json_schema()
    schema.get("properties", {}).pop("path", None)  # server-side files are not offered over the API
    return OrbitKindOut(kind=kind, description=(model.__doc__ or "").strip().splitlines()[0], parameters=schema)


def build(spec: OrbitSpec) -> Any:
    """The orbit of ``spec``, or 422 with the offending parameter."""
    if spec.params.get("path") is not None:
        raise Invalid(
            "server file paths are not accepted over the API",
            advice="give the waypoints as 'points' instead",
            details=[FieldProblem(field="params.path", reason="give 'points' instead")],
        )
    try:
        model = ORBIT_KINDS[spec.kind].model_validate(spec.params)
    except ValidationError as exc:
        details = [
            FieldProblem(field="params." + d.field, reason=d.reason) for d in validation_details(list(exc.errors()))
        ]
        raise Invalid("; ".join(f"{d.field}: {d.reason}" for d in details[:5]), details=details) from None
    if int(model.n_frames) > PREVIEW_MAX_FRAMES:
        raise Invalid(
            f"too many frames for a preview (at most {PREVIEW_MAX_FRAMES})",
            advice=f"preview at most {PREVIEW_MAX_FRAMES} frames",
            details=[FieldProblem(field="params.n_frames", reason=f"at most {PREVIEW_MAX_FRAMES}")],
        )
    try:
        return make_orbit(spec.kind, **model.model_dump(exclude_none=True))
    except OrbitError as exc:
        raise Invalid(str(exc), details=[FieldProblem(field="params", reason=str(exc))]) from None


@router.get("", response_model=list[OrbitKindOut], summary="Orbit kinds and their parameter schemas")
def list_kinds(_: Reader) -> list[OrbitKindOut]:
    """Every orbit kind with the JSON schema of its parameters."""
    return [_describe(k) for k in ORBIT_KINDS]


@router.get("/{kind}", response_model=OrbitKindOut, summary="One orbit kind")
def get_kind(kind: str, _: Reader) -> OrbitKindOut:
    """The parameter schema of one orbit kind."""
    if kind not in ORBIT_KINDS:
        raise NotFound(f"no orbit kind {kind[:40]!r}", advice=f"use one of {', '.join(ORBIT_KINDS)}")
    return _describe(kind)


@router.post("/validate", response_model=OrbitSummary, summary="Validate orbit parameters")
def validate(spec: OrbitSpec, _: Reader) -> OrbitSummary:
    """200 with the normalised parameters and covered ranges, or 422 naming the parameter and why."""
    orbit = build(spec)
    th, ph = orbit.theta_deg, orbit.phi_deg
    steps = orbit.step_sizes()
    return OrbitSummary(
        kind=spec.kind,
        params=orbit.params,
        n_frames=orbit.n_frames,
        n_segments=orbit.n_segments,
        rotation_deg=(float(th.min()), float(th.max())),
        tilt_deg=(float(ph.min()), float(ph.max())),
        step_deg=(float(np.degrees(steps[0])), float(np.degrees(steps[1]))),
    )


@router.post(
    "/preview",
    summary="Preview an orbit (PNG)",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "tilt against rotation, and both against frame"}},
)
def preview(spec: OrbitSpec, _: Reader) -> Response:
    """A PNG plot: tilt against rotation (the orbit's path), and both angles against frame index."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    orbit = build(spec)
    fig = Figure(figsize=(8, 3.2), dpi=90)
    ax1, ax2 = fig.subplots(1, 2)
    ax1.plot(orbit.theta_deg, orbit.phi_deg, ".", ms=2)
    ax1.set(xlabel="rotation (deg)", ylabel="tilt (deg)", title=f"{spec.kind}: {orbit.n_frames} frames")
    idx = np.arange(orbit.n_frames)
    ax2.plot(idx, orbit.theta_deg, label="rotation")
    ax2.plot(idx, orbit.phi_deg, label="tilt")
    ax2.set(xlabel="frame", ylabel="deg")
    ax2.legend(loc="best", fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return Response(buf.getvalue(), media_type="image/png")
