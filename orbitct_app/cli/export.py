"""``orbitct export dicom`` (a reconstruction as a DICOM CT image series), ``orbitct export xa`` (a C-arm scan's run as
DICOM XA, as the C-arm exports it), ``orbitct export nxtomo`` (a scan as NXtomo) and, from ``export_toolkit``, the
geometry for other reconstruction toolkits."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from orbitct.dicom import DicomSeriesOptions
from orbitct_app.cli.export_toolkit import TOOLKIT_COMMANDS
from orbitct_app.cli.failure import Failure
from orbitct_app.cli.model_options import model_from, options_from


@click.group()
def export() -> None:
    """Write what a scan file holds in formats other tools read."""


for _command in TOOLKIT_COMMANDS:
    export.add_command(_command)


@export.command("dicom")
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--recon", "name", required=True, help="Name of the reconstruction under /recon (see `orbitct inspect`).")
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder for the series (one CT000001.dcm ... per axial slice); created if needed, must be empty.",
)
@options_from(DicomSeriesOptions)
def dicom(scan: Path, name: str, out_dir: Path, **given: Any) -> None:
    """Export reconstruction NAME of SCAN as a CT series (or one Enhanced CT object) in Hounsfield units (the object
    frame as patient frame)."""
    from orbitct.geometry import VolumeGrid
    from orbitct.scanfile import ScanFile, ScanFileError
    from orbitct.scanfile.xa import patient_sides_caveat
    from recon.dicom import SeriesInfo, export_dicom_ct, export_enhanced_ct
    from recon.errors import ReconError

    options = model_from(DicomSeriesOptions, given)

    if out_dir.exists() and any(out_dir.iterdir()):
        raise Failure(f"{out_dir} is not empty", "conflict", "give a new or empty folder for the series")
    try:
        with ScanFile(scan) as sf:
            volume, attrs = sf.read_recon(name)
            calibrated = sf.has_geometry("calibrated")
            caveat = patient_sides_caveat(sf.attrs_json("provenance", "import_assumptions_json").get("assumed", []))
    except ScanFileError as exc:
        raise click.ClickException(str(exc)) from None
    grid = VolumeGrid(tuple(volume.shape), tuple(attrs["voxel_mm"]), tuple(attrs["origin_mm"]))
    geometry = str(attrs.get("geometry", "?"))
    provenance = f"{str(attrs.get('algorithm', '?')).upper()} {geometry} geometry"
    if geometry == "calibrated" and calibrated:
        provenance += " (BB calibration)"
    info = SeriesInfo.from_options(
        options, description=f"orbitct {name}: {provenance}", patient_id=scan.stem, comments=caveat
    )
    if caveat:
        click.echo(f"warning: {caveat} (in every image's ImageComments)", err=True)
    try:
        if options.enhanced:
            path = export_enhanced_ct(volume, grid, out_dir / "CT_ENHANCED.dcm", info)
        else:
            files = export_dicom_ct(volume, grid, out_dir, info)
    except ReconError as exc:
        raise click.ClickException(str(exc)) from None
    nz, ny, nx = volume.shape
    if options.enhanced:
        click.echo(f"wrote {path}: one Enhanced CT object of {nz} frames of {nx}x{ny} px: {info.description}")
        return
    click.echo(
        f"wrote {len(files)} CT slices of {nx}x{ny} px ({grid.voxel_mm[0]:g} x {grid.voxel_mm[1]:g} mm, "
        f"{grid.voxel_mm[2]:g} mm apart) to {out_dir}: {info.description}"
    )


@export.command("nxtomo")
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="The NXtomo file to write (.nx)."
)
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def nxtomo(scan: Path, out: Path, overwrite: bool) -> None:
    """Export SCAN as NXtomo (NeXus): frames, image keys, angles, distances, per-frame transformations, and the full
    per-view geometry in an ``orbitct`` collection."""
    from orbitct.scanfile import ScanFileError
    from orbitct.scanfile.nxtomo import ENTRY, export_nxtomo

    try:
        path = export_nxtomo(scan, out, overwrite=overwrite)
    except ScanFileError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"wrote {path} (NXtomo entry /{ENTRY})")


@export.command("xa")
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="The XA file to write (.dcm)."
)
@click.option(
    "--frames",
    "part",
    default=None,
    help="Only projections FIRST:LAST (0-based, LAST excluded): one run of an orbit acquired as several.",
)
@click.option(
    "--kind",
    type=click.Choice(["xa", "xrf", "enhanced-xa"]),
    default="xa",
    show_default=True,
    help="Classic XA, XRF, or Enhanced XA (per-frame functional groups).",
)
def xa(scan: Path, out: Path, part: str | None, kind: str) -> None:
    """Write the projections of a C-arm scan as one multi-frame DICOM run (positioner angles per frame, distances,
    pixel spacing), as a C-arm's own export does; `orbitct import dicom` reads it back."""
    from orbitct.scanfile import ScanFileError
    from orbitct.scanfile.xa import write_xa_run

    span = None
    if part is not None:
        try:
            first, last = (int(x) for x in part.split(":"))
        except ValueError:
            raise click.BadParameter(f"expected FIRST:LAST (e.g. 0:100), got {part!r}", param_hint="--frames") from None
        span = (first, last)
    if out.exists():
        raise Failure(f"{out} exists", "conflict", "choose another name")
    try:
        path = write_xa_run(scan, out, part=span, kind=kind)  # type: ignore[arg-type]
    except ScanFileError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"wrote {path} ({kind})")
