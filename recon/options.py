"""The options of a reconstruction, in one place: names, units, limits and defaults.

:class:`ReconstructionOptions` is what :func:`recon.reconstruct_scan` takes; ``orbitct reconstruct`` makes its
options from it and the REST service's request body extends it, so the same request gets the same answer from the
command line, the API and Python.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

#: the largest volume a request may ask for (4 GiB of float32 voxels); memory is checked again before any work
MAX_VOXELS = 1024**3
Algorithm = Literal["fdk", "pwls"]
GeometryName = Literal["calibrated", "nominal", "truth"]
StreamMode = Literal["auto", "memory", "file"]
Device = Literal["auto", "cpu", "cuda"]
DEFAULT_BETA = 0.01  # PWLS relative penalty strength: times the median data curvature (recon.pwls)


class ReconstructionOptions(BaseModel):
    """How to reconstruct a scan: algorithm, geometry, grid, solver and metal artefact reduction."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    algorithm: Algorithm = Field("fdk", description="FDK (seconds) or PWLS with separable paraboloidal surrogates")
    geometry: GeometryName = Field(
        "calibrated", description="which per-view geometry of the scan file (truth exists only in simulated scans)"
    )
    voxel_mm: float | None = Field(
        None, gt=0.005, le=20.0, description="isotropic voxel size in mm (default: the detector pitch at the isocenter)"
    )
    shape: list[Annotated[int, Field(ge=4, le=2048)]] | None = Field(
        None, min_length=3, max_length=3, description="volume shape [nz, ny, nx], centred on the isocenter"
    )
    fit: Literal["object", "fov"] = Field(
        "object",
        description="without a shape: fit the grid to the object (found in a coarse reconstruction) or cover the "
        "whole field of view",
    )
    iterations: int = Field(50, ge=1, le=500, description="PWLS iterations (passes over the subsets)")
    subsets: int = Field(1, ge=1, le=64, description="PWLS ordered subsets (faster convergence)")
    momentum: bool = Field(False, description="PWLS: ordered subsets with Nesterov's momentum (with subsets, e.g. 12)")
    final_cost: bool = Field(
        False,
        description="PWLS: also compute the cost at the result (one more forward projection of every view); without "
        "it the last cost reported is the one before the last iteration",
    )
    beta: float = Field(DEFAULT_BETA, ge=0.0, le=1e6, description="PWLS relative penalty strength (larger: smoother)")
    neighbourhood: Literal[1, 2] = Field(1, description="PWLS penalty neighbourhood: 1 (6 neighbours) or 2 (26)")
    window: Literal["ram-lak", "shepp-logan", "cosine", "hann"] = Field(
        "hann", description="ramp filter window of FDK (and of the PWLS start image)"
    )
    mar: bool = Field(False, description="metal artefact reduction (screws, BBs)")
    mar_method: Literal["reprojection", "threshold"] = Field(
        "reprojection",
        description="MAR: find metal traces by reprojecting the metal of a first FDK, or by thresholding the line "
        "integrals against their local background",
    )
    metal_mu_per_mm: float = Field(
        0.1, gt=0.0, le=10.0, description="MAR: voxels of a first FDK above this attenuation (1/mm) are metal"
    )
    mar_threshold: float = Field(
        0.5, gt=0.0, le=100.0, description="MAR by threshold: line integral above its local background"
    )
    stream: StreamMode = Field(
        "auto",
        description="PWLS data: held in memory, or re-read from the scan file each iteration (three volumes of "
        "memory, slower); auto: memory while it fits",
    )
    device: Device = Field(
        "auto",
        description="where the projectors, FDK's filtering and back-projection and the PWLS steps run: cpu, cuda "
        "(one NVIDIA GPU; the gpu extra) or auto (the GPU when one is usable, else the CPU)",
    )
    name: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$",
        description="name under /recon in the scan file (default ALGORITHM_GEOMETRY[_mar])",
    )
    overwrite: bool = Field(False, description="replace a reconstruction of that name already in the scan file")
    accept_failed_geometry: bool = Field(
        False,
        description="reconstruct from a calibrated geometry that failed its quality check (refused otherwise); "
        "recorded with the volume and shown wherever it is shown",
    )
    max_minutes: float | None = Field(
        None,
        gt=0.0,
        le=10080.0,
        description="refuse, before any work, a reconstruction estimated to take longer (none: no limit)",
    )

    @field_validator("shape", mode="before")
    @classmethod
    def _three_sizes(cls, value: object) -> object:
        if value is not None and (not isinstance(value, list | tuple) or len(value) != 3):
            raise ValueError(f"expected three sizes NZ,NY,NX (e.g. 128,256,256), got {value!r}")
        return value

    @model_validator(mode="after")
    def _size(self) -> ReconstructionOptions:
        if self.shape is not None and math.prod(self.shape) > MAX_VOXELS:
            raise ValueError(f"shape {list(self.shape)} has more than {MAX_VOXELS} voxels (1024^3)")
        return self

    @property
    def recon_name(self) -> str:
        """The name under ``/recon`` the result gets."""
        return self.name or f"{self.algorithm}_{self.geometry}" + ("_mar" if self.mar else "")

    @property
    def max_seconds(self) -> float | None:
        """The time limit in seconds, or None."""
        return None if self.max_minutes is None else 60.0 * self.max_minutes
