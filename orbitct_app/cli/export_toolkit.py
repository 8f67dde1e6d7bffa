"""``orbitct export astra | tomosipo | leap | diffct | tigre | cil | rtk``: a scan's per-view geometry for another toolkit."""

from __future__ import annotations

from pathlib import Path

import click

from orbitct.toolkits import TOOLKIT_NAMES, GeometryExportOptions
from orbitct_app.cli.failure import Failure, fail


def _command(toolkit: str) -> click.Command:
    label = TOOLKIT_NAMES[toolkit]
    suffix = ".xml" if toolkit == "rtk" else ".json"
    fields = GeometryExportOptions.model_fields

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
        help=f"Which of the scan's geometries: {fields['geometry'].description}.",
    )
    @click.option("--accept-failed-geometry", is_flag=True, help=f"{fields['accept_failed_geometry'].description}.")
    def command(scan: Path, out: Path, name: str | None, accept_failed_geometry: bool) -> None:
        from orbitct.scanfile import ScanFileError
        from recon.errors import FailedGeometryError, ReconError
        from recon.geometry_export import export_scan_geometry

        if out.exists():
            raise Failure(f"{out} exists", "conflict", "choose another name or remove it")
        options = GeometryExportOptions(toolkit=toolkit, geometry=name, accept_failed_geometry=accept_failed_geometry)
        try:
            export = export_scan_geometry(scan, options)
        except FailedGeometryError as exc:
            fail(exc.what, "failed_quality_check", exc.advice("pass --accept-failed-geometry"))
        except (ReconError, ScanFileError) as exc:
            raise click.ClickException(str(exc)) from None
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(export.text)
        click.echo(f"wrote {out}: {export.summary}")
        if export.warning is not None:
            click.echo(f"warning: {export.warning}", err=True)

    command.__doc__ = (
        f"Write SCAN's per-view geometry for {label}: the call it feeds and its arguments in {label}'s conventions "
        "(docs: How-to > Reconstruct with another toolkit)."
    )
    return click.command(toolkit)(command)


#: one command per toolkit, added to ``orbitct export``
TOOLKIT_COMMANDS = [_command(toolkit) for toolkit in TOOLKIT_NAMES]
