"""A scan's per-view geometry written for another reconstruction toolkit: the document that results from
:class:`~orbitct.toolkits.GeometryExportOptions`. ``orbitct export <toolkit>`` and ``GET
/scans/{id}/geometry/export`` both call :func:`export_scan_geometry`."""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from orbitct.scanfile import ScanFile
from orbitct.toolkits import APPROXIMATION_WARN_PX, TOOLKIT_NAMES, GeometryExportOptions
from recon.errors import FailedGeometryError
from recon.pipeline import failed_geometry_reasons


@dataclass(frozen=True)
class GeometryExport:
    """One written export: the document (JSON, or RTK's XML), what it holds, and how exact it is."""

    text: str
    media_type: str
    suffix: str
    toolkit: str
    geometry: str
    views: int
    approximation_px: float
    summary: str

    @property
    def warning(self) -> str | None:
        """Said when the toolkit cannot hold the geometry exactly (orthogonal detector axes, one pixel size)."""
        if self.approximation_px <= APPROXIMATION_WARN_PX:
            return None
        label = TOOLKIT_NAMES[self.toolkit]
        return (
            f"{label} cannot hold this geometry exactly (orthogonal detector axes, one pixel size): points land up "
            f"to {self.approximation_px:.3g} px from where orbitct projects them"
        )


def export_scan_geometry(
    scan: str | os.PathLike[str], options: GeometryExportOptions, *, name: str = ""
) -> GeometryExport:
    """The export ``options`` asks for of ``scan`` (``name``: how to call the scan in sentences, its file name by
    default). A failed calibrated geometry is refused (:class:`FailedGeometryError`) unless accepted; views
    without geometry are refused (:class:`~recon.errors.ReconError`)."""
    scan = Path(scan)
    with ScanFile(scan) as sf:
        chosen = options.geometry or ("calibrated" if sf.has_geometry("calibrated") else "nominal")
        reasons = failed_geometry_reasons(sf, chosen)
        if reasons is not None and not options.accept_failed_geometry:
            raise FailedGeometryError(name or scan.name, reasons)
        geometry = sf.geometry(chosen)[sf.projection_indices]
    label = TOOLKIT_NAMES[options.toolkit]
    if options.toolkit == "rtk":
        from recon.export import write_rtk_geometry

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "geometry.xml"
            layout = write_rtk_geometry(geometry, path)
            text = path.read_text()
        summary = (
            f"{len(geometry)} views of the {chosen} geometry for RTK (projection images with rows flipped, spacing "
            f"{layout['spacing']} mm, origin {layout['origin']} mm)"
        )
        return GeometryExport(text, "application/xml", ".xml", "rtk", chosen, len(geometry), 0.0, summary)
    from recon.toolkits import toolkit_geometry

    document = toolkit_geometry(geometry, options.toolkit)
    document["orbitct"] = {"scan": name or scan.name, "geometry": chosen}
    off = float(document["approximation_px"])
    how = "exact" if off < 1e-6 else f"within {off:.3g} px of orbitct's projection"
    summary = f"{document['views']} views of the {chosen} geometry for {label} ({how})"
    text = json.dumps(document, indent=1) + "\n"
    return GeometryExport(text, "application/json", ".json", options.toolkit, chosen, len(geometry), off, summary)
