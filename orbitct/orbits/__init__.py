"""Named, parameterised orbits: circular, sawtooth, dcarc, multiarc, waypoints (``make_orbit``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from pydantic import BaseModel, ValidationError

from orbitct.orbits import shapes
from orbitct.orbits.errors import OrbitError
from orbitct.orbits.orbit import Orbit
from orbitct.orbits.params import (
    MAX_FRAMES,
    MAX_ROTATION_DEG,
    MAX_TILT_DEG,
    ORBIT_KINDS,
    PRESETS,
    CircularParams,
    DCArcParams,
    MultiArcParams,
    RotationArc,
    SawtoothParams,
    TiltArc,
    WaypointsParams,
)
from orbitct.orbits.waypoints import read_waypoints

__all__ = [
    "MAX_FRAMES",
    "MAX_ROTATION_DEG",
    "MAX_TILT_DEG",
    "ORBIT_KINDS",
    "PRESETS",
    "CircularParams",
    "DCArcParams",
    "MultiArcParams",
    "Orbit",
    "OrbitError",
    "RotationArc",
    "SawtoothParams",
    "TiltArc",
    "WaypointsParams",
    "describe_kinds",
    "make_orbit",
    "orbit_from_json",
    "read_waypoints",
    "validate_params",
]

_BUILDERS: dict[str, Callable[[Any], shapes.Angles]] = {
    "circular": shapes.circular,
    "sawtooth": shapes.sawtooth,
    "dcarc": shapes.dcarc,
    "multiarc": shapes.multiarc,
    "waypoints": shapes.waypoints,
}


def _explain(name: str, exc: ValidationError) -> OrbitError:
    parts = []
    for e in exc.errors():
        loc = ".".join(str(x) for x in e["loc"]) or "parameters"
        parts.append(f"{loc}: {e['msg']}")
    allowed = ", ".join(ORBIT_KINDS[name].model_fields)
    return OrbitError(f"orbit {name!r}: " + "; ".join(parts) + f" (parameters: {allowed})")


def validate_params(name: str, **params: Any) -> BaseModel:
    """The validated parameter model of orbit kind ``name`` (raises :class:`OrbitError`)."""
    if name not in ORBIT_KINDS:
        raise OrbitError(f"unknown orbit {name!r}; known orbits are {sorted(ORBIT_KINDS)}")
    try:
        model = ORBIT_KINDS[name](**params)
        if isinstance(model, WaypointsParams) and model.points is None:
            pts = read_waypoints(str(model.path))
            model = WaypointsParams(n_frames=model.n_frames, path=model.path, points=pts)
    except ValidationError as exc:
        raise _explain(name, exc) from None
    return model


def make_orbit(name: str, **params: Any) -> Orbit:
    """Build orbit ``name`` from keyword parameters (degrees; see ``ORBIT_KINDS[name]``)."""
    model = validate_params(name, **params)
    try:
        theta, phi, seg = _BUILDERS[name](model)
    except ValueError as exc:
        raise OrbitError(f"orbit {name!r}: {exc}") from None
    return Orbit(name=name, params=model.model_dump(mode="json", exclude_none=True), theta=theta, phi=phi, segment=seg)


def orbit_from_json(data: dict[str, Any]) -> Orbit:
    """Rebuild an orbit from :meth:`Orbit.to_json` (or a scan file's ``/orbit`` name and params)."""
    return make_orbit(str(data["name"]), **dict(data.get("params") or {}))


def describe_kinds() -> dict[str, str]:
    """One line per orbit kind (for ``orbitct orbit list``)."""
    return {k: (m.__doc__ or "").strip().splitlines()[0] for k, m in ORBIT_KINDS.items()}
