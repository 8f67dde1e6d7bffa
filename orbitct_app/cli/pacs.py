"""``orbitct pacs send|find|get``: DICOM objects to and from a PACS node (``dicom://AE@host:port``)."""

from __future__ import annotations

from pathlib import Path

import click

from orbitct_app.cli.failure import Failure


def _node(uri: str):
    from orbitct_app.pacs import PacsError, PacsNode

    try:
        return PacsNode.parse(uri)
    except PacsError as exc:
        raise click.BadParameter(str(exc)) from None


@click.group()
def pacs() -> None:
    """Send series to a PACS, find series on it, fetch them."""


@pacs.command("send")
@click.argument("inputs", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--to", "to", required=True, help="The node: dicom://AE_TITLE@host:port.")
@click.option("--calling-aet", default="ORBITCT", show_default=True, help="orbitct's own AE title.")
def send_cmd(inputs: tuple[Path, ...], to: str, calling_aet: str) -> None:
    """C-STORE the DICOM files in INPUTS (files, or folders of .dcm files), e.g. from `orbitct export dicom`."""
    from orbitct_app.pacs import PacsError, send

    node = _node(to)
    files = [p for i in inputs for p in (sorted(i.glob("*.dcm")) if i.is_dir() else [i])]
    if not files:
        raise Failure(
            f"no .dcm files in {', '.join(map(str, inputs))}", "not_found", "give the files or folders the series is in"
        )
    try:
        n = send(files, node, calling_aet)
    except PacsError as exc:
        raise Failure(str(exc), "bad_gateway") from None
    click.echo(f"stored {n} object(s) on {node}")


@pacs.command("find")
@click.option("--on", "on", required=True, help="The node: dicom://AE_TITLE@host:port.")
@click.option("--patient-id", default="", help="Only this patient.")
@click.option("--modality", default="", help="Only this modality (CT, XA, ...).")
@click.option("--calling-aet", default="ORBITCT", show_default=True)
def find_cmd(on: str, patient_id: str, modality: str, calling_aet: str) -> None:
    """List the series on the node (C-FIND): series UID, modality, instances, patient, description."""
    from orbitct_app.pacs import PacsError, find_series

    node = _node(on)
    match = {k: v for k, v in (("PatientID", patient_id), ("Modality", modality)) if v}
    try:
        found = find_series(node, calling_aet, **match)
    except PacsError as exc:
        raise Failure(str(exc), "bad_gateway") from None
    for s in found:
        click.echo(
            f"{s['SeriesInstanceUID']}  {s['Modality']}  {s['NumberOfSeriesRelatedInstances'] or '?'} instance(s)  "
            f"{s['PatientID']}  {s['SeriesDescription']}"
        )
    click.echo(f"{len(found)} series on {node}")


@pacs.command("get")
@click.argument("series_uid")
@click.option("--from", "source", required=True, help="The node: dicom://AE_TITLE@host:port.")
@click.option(
    "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Folder for the files."
)
@click.option("--calling-aet", default="ORBITCT", show_default=True)
def get_cmd(series_uid: str, source: str, out_dir: Path, calling_aet: str) -> None:
    """Fetch series SERIES_UID (C-GET) into OUT; an XA run then imports with `orbitct import dicom OUT`."""
    from orbitct_app.pacs import PacsError, find_series, get_series

    node = _node(source)
    try:
        hits = find_series(node, calling_aet, SeriesInstanceUID=series_uid)
        if not hits:
            raise PacsError(f"{node} has no series {series_uid}")
        files = get_series(node, hits[0]["StudyInstanceUID"], series_uid, out_dir, calling_aet)
    except PacsError as exc:
        raise Failure(str(exc), "bad_gateway") from None
    click.echo(f"fetched {len(files)} file(s) of series {series_uid} into {out_dir}")
