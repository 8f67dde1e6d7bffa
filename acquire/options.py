"""The options of a scan, in one place: names, units, limits and defaults.

:class:`ScanOptions` is what :class:`acquire.runner.ScanRequest` is checked against; ``orbitct scan`` makes its
options from it and the REST service's request body (``POST /scans``) extends it, so the same scan gets the same
answer from the command line, the API and Python. Where the scan runs (configuration, output file, twins) is not an
option of the scan: each interface says it its own way.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from acquire.errors import AcquireError
from orbitct.errorprofiles import PROFILE_NAMES
from orbitct.options import option_problems
from orbitct.orbits import ORBIT_KINDS

MAX_FRAMES = 100_000


class ScanOptions(BaseModel):
    """What to scan and how: orbit and its parameters, frames, injected motion errors, mode, frame rate."""

    # not strict: Python's numbers (numpy's too) are taken as they are; the REST request (JSON) is strict
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    orbit: str = Field("sawtooth", description="orbit kind: " + ", ".join(ORBIT_KINDS) + " (parameters: orbitct orbit)")
    orbit_params: dict[str, Any] = Field(
        default_factory=dict, description="the orbit's parameters (degrees), checked by the orbit's own model"
    )
    frames: int | None = Field(
        None, ge=2, le=MAX_FRAMES, description="projection frames (default: the orbit's n_frames)"
    )
    errors: Literal["none", "bench", "custom"] = Field(
        "none",
        description="motion errors injected on top of the orbit, for studies on the twins: none, bench (the "
        "published profile) or custom (with its error parameters); never on by default",
    )
    error_params: dict[str, Any] = Field(
        default_factory=dict, description="parameters of the custom error profile (amplitudes in deg and mm)"
    )
    seed: int = Field(0, ge=0, le=2**32 - 1, description="seed of the error profile's noise")
    mode: Literal["step", "continuous"] = Field(
        "step", description="step: move, settle, expose; continuous: constant rotation, exposures triggered at angles"
    )
    frame_rate_hz: float | None = Field(
        None,
        gt=0.0,
        le=1000.0,
        description="frames per second in continuous mode (default: the configuration's exposure.frame_rate_hz); "
        "the pre-flight checks the motion keeps up",
    )

    @field_validator("orbit")
    @classmethod
    def _known_orbit(cls, orbit: str) -> str:
        if orbit not in ORBIT_KINDS:
            raise ValueError(f"unknown orbit {orbit!r}; choose one of {', '.join(ORBIT_KINDS)}")
        return orbit


assert set(PROFILE_NAMES) == {"none", "bench", "custom"}, "ScanOptions.errors lists the error profiles"


def checked_scan_options(**options: Any) -> ScanOptions:
    """:class:`ScanOptions` from keyword ``options``, or :class:`AcquireError` naming each option that is wrong."""
    try:
        return ScanOptions.model_validate(options)
    except ValidationError as exc:
        raise AcquireError(option_problems(exc, ScanOptions)) from None
