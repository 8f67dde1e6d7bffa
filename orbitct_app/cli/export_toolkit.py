"""``orbitct export astra | tomosipo | leap | diffct | tigre | cil | rtk``: a scan's per-view geometry for another toolkit."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import click

from orbitct_app.cli.failure import Failure, fail

if TYPE_CHECKING:
    from orbitct.geometry import ViewGeometry

APPROXIMATION_WARN_PX = 0.05  # an export that moves a projected point further than this says so
TOOLKIT_NAMES = {
    "astra": "ASTRA",
    "tomosipo": "tomosipo",
    "leap": "LEAP",
    "diffct": "diffct",
    "tigre": "TIGRE",
    "cil": "CIL",
    "rtk": "RTK",
}


def _geometry(scan: Path, name: str | None, accept_failed: bool) -> tuple[ViewGeometry, str]:
    """The scan's geometry ``name`` (default: calibrated when the scan has one, else nominal), a failed calibrated
    one refused unless ``accept_failed``."""
    from orbitct.scanfile import ScanFile, ScanFileError
    from recon.errors import FailedGeometryError
    from recon.pipeline import failed_geometry_reasons

    try:
        with ScanFile(scan) as sf:
            chosen = name or ("calibrated" if sf.has_geometry("calibrated") else "nominal")
            reasons = failed_geometry_reasons(sf, chosen)
            if reasons is not None and not accept_failed:
                exc = FailedGeometryError(scan.name, reasons)
                fail(exc.what, "failed_quality_check", exc.advice("pass --accept-failed-geometry"))
            return sf.geometry(chosen)[sf.projection_indices], chosen
    except ScanFileError as exc:
        raise click.ClickException(str(exc)) from None


def _command(toolkit: str) -> click.Command:
    label = TOOLKIT_NAMES[toolkit]
    suffix = ".xml" if toolkit == "rtk" else ".json"

    @click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
    @click.option(
        "--out",
        required=True,
        type=click.Path(dir_okay=False, path_type=Path),
        help=f"The file to write ({suffix}).",
    )
    @click.option(
        "--geometry",
        "name",
        type=click.Choice(["calibrated", "nominal", "truth"]),
        default=None,
        help="Which of the scan's geometries (default: calibrated when it has one, else nominal).",
    )
    @click.option(
        "--accept-failed-geometry",
        is_flag=True,
        help="Export a calibrated geometry that failed its quality check anyway.",
    )
    def command(scan: Path, out: Path, name: str | None, accept_failed_geometry: bool) -> None:
        from recon.errors import ReconError

        if out.exists():
            raise Failure(f"{out} exists", "conflict", "choose another name or remove it")
        geometry, chosen = _geometry(scan, name, accept_failed_geometry)
        try:
            if toolkit == "rtk":
                from recon.export import write_rtk_geometry

                layout = write_rtk_geometry(geometry, out)
                click.echo(
                    f"wrote {out}: {len(geometry)} views of the {chosen} geometry for RTK (projection images with "
                    f"rows flipped, spacing {layout['spacing']} mm, origin {layout['origin']} mm)"
                )
                return
            from recon.toolkits import toolkit_geometry

            document = toolkit_geometry(geometry, toolkit)  # type: ignore[arg-type]
        except ReconError as exc:
            raise click.ClickException(str(exc)) from None
        document["orbitct"] = {"scan": scan.name, "geometry": chosen}
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(document, indent=1) + "\n")
        off = document["approximation_px"]
        how = "exact" if off < 1e-6 else f"within {off:.3g} px of orbitct's projection"
        click.echo(f"wrote {out}: {document['views']} views of the {chosen} geometry for {label} ({how})")
        if off > APPROXIMATION_WARN_PX:
            click.echo(
                f"warning: {label} cannot hold this geometry exactly (orthogonal detector axes, one pixel size): points "
                f"land up to {off:.3g} px from where orbitct projects them",
                err=True,
            )

    command.__doc__ = (
        f"Write SCAN's per-view geometry for {label}: the call it feeds and its arguments in {label}'s conventions "
        "(docs: How-to > Reconstruct with another toolkit)."
    )
    return click.command(toolkit)(command)


#: one command per toolkit, added to ``orbitct export``
TOOLKIT_COMMANDS = [_command(toolkit) for toolkit in TOOLKIT_NAMES]
