"""``orbitct reconstruct``: FDK or PWLS reconstruction of a scan file into ``/recon/<name>``."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from orbitct_app.cli.progress import ProgressBar
from orbitct_app.cli.values import FiniteFloat

if TYPE_CHECKING:
    from recon import ReconResult


def _shape(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[int, int, int] | None:
    if value is None:
        return None
    try:
        parts = tuple(int(p) for p in value.replace("x", ",").split(","))
    except ValueError:
        parts = ()
    if len(parts) != 3 or min(parts) < 1:
        raise click.BadParameter(f"expected three positive integers NZ,NY,NX (e.g. 128,256,256), got {value!r}")
    return parts  # type: ignore[return-value]


@click.command()
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--algorithm", type=click.Choice(["fdk", "pwls"]), default="pwls", show_default=True)
@click.option(
    "--geometry",
    type=click.Choice(["calibrated", "nominal", "truth"]),
    default="calibrated",
    show_default=True,
    help="Which per-view geometry of the scan to use (truth exists only in simulated scans).",
)
@click.option(
    "--voxel-mm",
    type=FiniteFloat(),
    default=None,
    help="Isotropic voxel size in mm (default: detector pitch at the isocenter).",
)
@click.option(
    "--shape",
    callback=_shape,
    default=None,
    help="Volume shape NZ,NY,NX, centred on the isocenter (default: see --grid).",
)
@click.option(
    "--grid",
    "fit",
    type=click.Choice(["object", "fov"]),
    default="object",
    show_default=True,
    help="Without --shape: fit the grid to the object (found in a coarse reconstruction) or cover the whole "
    "field of view.",
)
@click.option("--iterations", type=click.IntRange(min=1), default=50, show_default=True, help="PWLS iterations.")
@click.option(
    "--beta", type=FiniteFloat(min=0), default=None, help="Relative penalty strength (default 0.01; larger = smoother)."
)
@click.option("--subsets", type=click.IntRange(min=1), default=1, show_default=True, help="Ordered subsets for PWLS.")
@click.option(
    "--momentum",
    is_flag=True,
    help="PWLS: ordered subsets with Nesterov's momentum (use with --subsets, "
    "e.g. 12; a fraction of the iterations reaches the plain solver's image).",
)
@click.option(
    "--window",
    type=click.Choice(["ram-lak", "shepp-logan", "cosine", "hann"]),
    default="hann",
    show_default=True,
    help="Ramp filter window for FDK (and the PWLS initial image).",
)
@click.option("--mar", is_flag=True, help="Metal artifact reduction (screws, BBs).")
@click.option(
    "--mar-method",
    type=click.Choice(["reprojection", "threshold"]),
    default="reprojection",
    show_default=True,
    help="Segment metal by thresholding line integrals or by reprojecting a thresholded first volume.",
)
@click.option(
    "--stream",
    type=click.Choice(["auto", "memory", "file"]),
    default="auto",
    show_default=True,
    help="PWLS data: hold projections and weights in memory, or re-read them from the scan file every "
    "iteration (three volumes of memory, slower); auto keeps them in memory while they fit.",
)
@click.option("--name", default=None, help="Name under /recon (default ALGORITHM_GEOMETRY[_mar]).")
@click.option("--overwrite", is_flag=True, help="Replace a reconstruction of the same name already in the file.")
@click.option(
    "--compare",
    "compare_geometry",
    type=click.Choice(["calibrated", "nominal", "truth"]),
    default=None,
    help="Also reconstruct with this geometry on the same grid and write both side by side in one grey "
    "window (<scan>_<name>_vs_<geometry>.png).",
)
@click.option(
    "--export",
    "export",
    type=click.Choice(["nifti", "tiff", "png"]),
    multiple=True,
    help="Also write the volume as NIfTI, TIFF stack or PNG slices (repeatable).",
)
@click.option(
    "--out-dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Folder for exports (default: next to the scan file).",
)
@click.option(
    "--max-minutes",
    type=FiniteFloat(min=0.0, min_open=True),
    default=10.0,
    show_default=True,
    envvar="ORBITCT_MAX_MINUTES",
    help="A reconstruction estimated to take longer asks first on a terminal, and is refused elsewhere.",
)
@click.option("--yes", is_flag=True, help="Start even when the estimate is above --max-minutes.")
@click.option(
    "--scheduler",
    default=None,
    envvar="ORBITCT_SCHEDULER",
    metavar="tcp://HOST:PORT",
    help="FDK and PWLS: split the views across the workers of this Dask scheduler (they read SCAN at the same path).",
)
def reconstruct(
    scan: Path,
    algorithm: str,
    geometry: str,
    voxel_mm: float | None,
    shape: tuple[int, int, int] | None,
    fit: str,
    iterations: int,
    beta: float | None,
    subsets: int,
    momentum: bool,
    window: str,
    mar: bool,
    mar_method: str,
    stream: str,
    name: str | None,
    overwrite: bool,
    compare_geometry: str | None,
    export: tuple[str, ...],
    out_dir: Path | None,
    max_minutes: float,
    yes: bool,
    scheduler: str | None,
) -> None:
    """Reconstruct SCAN (an orbitct scan file) and store the volume in it.

    The time it will take is estimated before anything large is allocated (from the projectors' speed on this
    machine now); above --max-minutes it asks on a terminal and refuses elsewhere, unless --yes."""
    import sys

    from orbitct.scanfile import ScanFileError
    from recon import (
        DEFAULT_BETA,
        ReconError,
        ReconExistsError,
        TooLongError,
        compare_reconstructions,
        reconstruct_scan,
    )

    cluster = _cluster(scheduler, mar)

    def run(limit_s: float | None) -> ReconResult:
        with ProgressBar() as bar:
            return reconstruct_scan(
                scan,
                algorithm=algorithm,
                geometry=geometry,
                voxel_mm=voxel_mm,
                shape=shape,
                iterations=iterations,
                beta=DEFAULT_BETA if beta is None else beta,
                mar=mar_method if mar else False,
                name=name,
                export=list(export),
                out_dir=out_dir,
                progress=bar,
                window=window,
                subsets=subsets,
                stream=stream,
                overwrite=overwrite,
                momentum=momentum,
                max_seconds=limit_s,
                fit=fit,
                cluster=cluster,
            )

    try:
        try:
            res = run(None if yes else 60.0 * max_minutes)
        except TooLongError as exc:
            if not (sys.stdin.isatty() and click.confirm(f"{exc}. Start it anyway?", default=False, err=True)):
                raise click.ClickException(f"{exc}; --yes starts it anyway, --max-minutes M sets the limit") from None
            res = run(None)
    except ReconExistsError as exc:
        raise click.ClickException(f"{exc}; --overwrite replaces it, --name NAME keeps both") from None
    except (ReconError, ScanFileError) as exc:
        raise click.ClickException(str(exc)) from None
    nz, ny, nx = res.volume_shape
    click.echo(
        f"{res.path}: /recon/{res.name}  {algorithm} with {geometry} geometry, {nz}x{ny}x{nx} voxels of "
        f"{res.voxel_mm[0]:g} mm, {res.elapsed_s:.1f} s (estimated {res.params['estimated_s']:.1f} s)"
    )
    click.echo(f"  grid: {res.params['grid_choice']}")
    if cluster is not None:
        click.echo(f"  views split across {res.params['cluster_workers']} Dask workers at {scheduler}")
    if res.cost:
        click.echo(f"  cost {res.cost[0]:.6g} -> {res.cost[-1]:.6g} over {len(res.cost) - 1} iterations")
    for p in res.exported:
        click.echo(f"  wrote {p}")
    for w in res.warnings:
        click.echo(f"warning: {w}", err=True)
    if compare_geometry is None:
        return
    if compare_geometry == geometry:
        raise click.UsageError(
            f"--compare {compare_geometry} is the geometry already reconstructed; compare with another"
        )
    try:
        with ProgressBar() as bar:
            other = reconstruct_scan(
                scan,
                algorithm=algorithm,
                geometry=compare_geometry,
                grid=res.grid,
                iterations=iterations,
                beta=DEFAULT_BETA if beta is None else beta,
                mar=mar_method if mar else False,
                name=f"{res.name}_vs_{compare_geometry}",
                progress=bar,
                window=window,
                subsets=subsets,
                stream=stream,
                overwrite=overwrite,
                momentum=momentum,
                cluster=cluster,
            )
        base = out_dir if out_dir is not None else res.path.parent
        base.mkdir(parents=True, exist_ok=True)
        figure = compare_reconstructions(
            res.path, [res.name, other.name], base / f"{res.path.stem}_{res.name}_vs_{compare_geometry}.png"
        )
    except ReconExistsError as exc:
        raise click.ClickException(f"{exc}; --overwrite replaces it") from None
    except (ReconError, ScanFileError) as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(
        f"  /recon/{other.name} with {compare_geometry} geometry, {other.elapsed_s:.1f} s; side by side: {figure}"
    )


def _cluster(address: str | None, mar: bool) -> object | None:
    """A client of the Dask scheduler at ``address`` for the views of FDK and PWLS; None without one."""
    import re

    if address is None:
        return None
    if not re.fullmatch(r"(tcp|tls)://[^\s/:]+:\d{1,5}", address):
        raise click.BadParameter(
            f"{address!r} is not a scheduler address; give tcp://HOST:PORT", param_hint="--scheduler"
        )
    if mar:
        raise click.UsageError(
            "--scheduler splits the views of FDK and PWLS across the cluster's workers; --mar runs "
            "on this machine (or as a job of `orbitct serve`, whose jobs run on the cluster)"
        )
    from distributed import Client

    try:
        client = Client(address, timeout=10, set_as_default=False)
    except Exception as exc:  # noqa: BLE001 - any failure to connect is the same answer
        raise click.ClickException(
            f"cannot reach the Dask scheduler at {address}: {type(exc).__name__}: {exc}"
        ) from None
    if not client.scheduler_info()["workers"]:
        try:
            client.wait_for_workers(1, timeout=30)
        except Exception:  # noqa: BLE001
            client.close()
            raise click.ClickException(
                f"the Dask scheduler at {address} has no workers (none joined within 30 s)"
            ) from None
    return client
