"""The reconstruction toolkits orbitct writes a scan's geometry for, and the options of such an export (the
export itself: :mod:`recon.geometry_export`). Here, apart from it, so that the command line and the service know
the toolkits without loading the reconstruction."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

ExportToolkit = Literal["astra", "tomosipo", "leap", "diffct", "tigre", "cil", "rtk"]
#: each toolkit's name as its own documentation writes it
TOOLKIT_NAMES: dict[str, str] = {
    "astra": "ASTRA",
    "tomosipo": "tomosipo",
    "leap": "LEAP",
    "diffct": "diffct",
    "tigre": "TIGRE",
    "cil": "CIL",
    "rtk": "RTK",
}
#: an export whose toolkit moves a projected point further than this (px) says so
APPROXIMATION_WARN_PX = 0.05


class GeometryExportOptions(BaseModel):
    """Which of a scan's geometries to write, for which toolkit."""

    model_config = ConfigDict(extra="forbid")

    toolkit: ExportToolkit = Field(description="the toolkit: " + ", ".join(TOOLKIT_NAMES))
    geometry: Literal["calibrated", "nominal", "truth"] | None = Field(
        None, description="which of the scan's geometries (default: calibrated when it has one, else nominal)"
    )
    accept_failed_geometry: bool = Field(
        False, description="write a calibrated geometry that failed its quality check anyway"
    )
