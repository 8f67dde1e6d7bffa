"""``orbitct plan bbs``: where to tape the BBs for an orbit, with the calibration accuracy each view can expect."""

from __future__ import annotations

from pathlib import Path

import click

from orbitct_app.bbplan import MOTION_ERRORS
from orbitct_app.cli.progress import ProgressBar
from orbitct_app.cli.values import SEED, FiniteFloat


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
@click.option("--orbit", "orbit_name", default=None, metavar="NAME", help="orbit kind (default: the experiment's)")
@click.option("--frames", type=click.IntRange(min=2), default=None, help="projections (default: the orbit's)")
@click.option("--bbs", "n_bbs", type=click.IntRange(min=4, max=40), default=8, show_default=True, help="BBs to place")
@click.option(
    "--target-px",
    type=FiniteFloat(min=0.0, min_open=True),
    default=None,
    help="instead of --bbs: the fewest BBs whose planned placement predicts at most this error in every view",
)
@click.option(
    "--max-bbs",
    type=click.IntRange(min=4, max=40),
    default=20,
    show_default=True,
    help="with --target-px: the most BBs to try",
)
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
    "--surface-threshold",
    type=FiniteFloat(),
    default=None,
    metavar="MU_PER_MM",
    help="with a volume: the attenuation (1/mm) above which a voxel is the object (default: Otsu's threshold)",
)
@click.option("--detector-size", type=click.IntRange(min=8, max=4096), default=768, show_default=True)
@click.option(
    "--errors",
    type=click.Choice(MOTION_ERRORS),
    default="none",
    show_default=True,
    help="the orbit's expected motion errors: a BB counts in a view only where it stays usable in three "
    "samples of this error profile (bench: the simulated bench's)",
)
@click.option(
    "--noise-px",
    type=FiniteFloat(min=0.0, min_open=True),
    default=0.1,
    show_default=True,
    help="centroid noise of the BB detection (a calibration reports it as centroid_noise_px)",
)
@click.option("--seed", type=SEED, default=0, show_default=True, help="the search's random start")
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="the plan (JSON); a picture is written beside it (.png)",
)
def bbs(
    experiment: str,
    orbit_name: str | None,
    frames: int | None,
    n_bbs: int,
    target_px: float | None,
    max_bbs: int,
    keep_out: tuple[object, ...],
    surface_source: str | None,
    surface_threshold: float | None,
    detector_size: int,
    errors: str,
    noise_px: float,
    seed: int,
    out: Path,
) -> None:
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

    try:
        surface = load_surface(surface_source, surface_threshold) if surface_source else None
        request = BBPlanRequest(
            experiment=experiment,
            orbit=orbit_name,
            frames=frames,
            n_bbs=n_bbs,
            detector_px=detector_size,
            noise_px=noise_px,
            seed=seed,
            keep_out=keep_out,
            target_px=target_px,
            max_bbs=max_bbs,
            surface=surface,
            errors=errors,
        )
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
