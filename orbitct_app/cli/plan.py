"""``orbitct plan bbs``: where to tape the BBs for an orbit, with the calibration accuracy each view can expect."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from orbitct_app.bbplan_options import BBPlanOptions
from orbitct_app.cli.model_options import model_from, options_from
from orbitct_app.cli.progress import ProgressBar

if TYPE_CHECKING:
    from calib.plan import KeepOut

#: the options whose flag is not the field's name
FLAGS = {"detector_px": "--detector-size", "surface_threshold_per_mm": "--surface-threshold"}


@click.group()
def plan() -> None:
    """Plan an acquisition before it runs."""


def _keep_out(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> tuple[object, ...]:
    from calib.plan import KeepOut

    try:
        return tuple(KeepOut.parse(v) for v in values)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


@plan.command("bbs")
@click.option(
    "--experiment",
    "-e",
    type=click.Choice(["A", "B", "C"], case_sensitive=False),
    required=True,
    help="The object (its surface, metal and BB size) and its default orbit.",
)
@options_from(BBPlanOptions, flags=FLAGS, exclude={"experiment", "keep_out"})
@click.option(
    "--keep-out",
    "keep_out",
    multiple=True,
    callback=_keep_out,
    metavar="FROM:TO,ZMIN:ZMAX",
    help="a patch of the surface without BBs: polar angles (deg, counterclockwise from +x) and heights (mm), "
    "e.g. 300:60,-20:10; repeat for more",
)
@click.option(
    "--surface",
    "surface_source",
    default=None,
    metavar="MESH|VOLUME|SCAN.h5#RECON|SHAPE",
    help="the object's surface instead of the experiment's cylinder: a mesh (.stl .obj .ply .off, mm, object "
    "frame), a prior volume (.nii/.nii.gz as orbitct writes it), a reconstruction in a scan file, or a shape "
    "in mm: cylinder:R,ZMIN:ZMAX, cylinder:A,B,ZMIN:ZMAX, ellipsoid:A,B,C[,ZMIN:ZMAX]",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="the plan (JSON); a picture is written beside it (.png)",
)
def bbs(experiment: str, keep_out: tuple[KeepOut, ...], surface_source: str | None, out: Path, **given: Any) -> None:
    """Search BB positions on the object's surface that minimise the predicted calibration error of the orbit's
    views (the worst views weighted), and compare with the experiment's own placement."""
    from orbitct_app.bbplan import (
        BBPlanError,
        BBPlanRequest,
        load_surface,
        make_bb_plan,
        plan_lines,
        write_bb_plan,
    )

    zones = [dataclasses.asdict(zone) for zone in keep_out]
    options = model_from(BBPlanOptions, {**given, "experiment": experiment, "keep_out": zones}, flags=FLAGS)
    out.parent.mkdir(parents=True, exist_ok=True)  # a folder that cannot be made is said before the search
    try:
        surface = load_surface(surface_source, options.surface_threshold_per_mm) if surface_source else None
        request = BBPlanRequest.from_options(options, surface)
        with ProgressBar() as bar:
            made = make_bb_plan(request, progress=bar)
    except BBPlanError as exc:
        raise click.ClickException(str(exc)) from None
    picture = write_bb_plan(made, out)
    for line in plan_lines(made):
        click.echo(line)
    for warning in made.warnings:
        click.echo(f"warning: {warning}", err=True)
    click.echo(f"wrote {out} and {picture}")
