"""``orbitct import dicom``: C-arm runs (DICOM XA) into a scan file with their nominal geometry."""

from __future__ import annotations

from pathlib import Path

import click

from orbitct.scanfile.xa import ANGLE_INCREMENTS, AngleIncrements
from orbitct_app.cli.failure import Failure


@click.group("import")
def import_group() -> None:
    """Read data from other formats into scan files."""


@import_group.command("dicom")
@click.argument("inputs", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="The scan file to write.")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
@click.option(
    "--angle-increments",
    type=click.Choice(ANGLE_INCREMENTS),
    default="auto",
    show_default=True,
    help="How a classic run stores its per-frame angle increments: offsets from the first frame, steps from the "
    "previous frame, absolute angles, or auto (read from the values; the choice is printed).",
)
def dicom(inputs: tuple[Path, ...], out: Path, overwrite: bool, angle_increments: AngleIncrements) -> None:
    """Import the XA runs in INPUTS (files, or folders of .dcm files) of one orbit, in acquisition order."""
    from orbitct.scanfile import ScanFile, ScanFileError
    from orbitct.scanfile.xa import import_xa

    files = [p for i in inputs for p in (sorted(i.glob("*.dcm")) if i.is_dir() else [i])]
    if not files:
        raise Failure(
            f"no .dcm files in {', '.join(map(str, inputs))}", "not_found", "give the files or folders the series is in"
        )
    try:
        path = import_xa(files, out, overwrite=overwrite, angle_increments=angle_increments)
        with ScanFile(path) as sf:
            n = sf.count_by_kind()["projection"]
            assumed = sf.attrs_json("provenance", "import_assumptions_json")["assumed"]
    except ScanFileError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"wrote {path}: {n} projections from {len(files)} run(s)")
    for line in assumed:
        click.echo(f"  assumed: {line}")
