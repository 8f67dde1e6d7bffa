"""``orbitct reconstruct``: FDK or PWLS reconstruction of a scan file into ``/recon/<name>``."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, get_args

import click

from orbitct_app.cli.failure import Failure, fail
from orbitct_app.cli.model_options import model_from, options_from
from orbitct_app.cli.progress import ProgressBar
from orbitct_app.cli.values import FiniteFloat
from recon.export import FORMATS
from recon.options import GeometryName, ReconstructionOptions

if TYPE_CHECKING:
    from recon import ReconResult


FLAGS = {"fit": "--grid"}  # the option's name where it is not the field's


@click.command()
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@options_from(ReconstructionOptions, flags=FLAGS, metavars={"shape": "NZ,NY,NX"}, exclude={"max_minutes"})
@click.option(
    "--compare",
    "compare_geometry",
    type=click.Choice(get_args(GeometryName)),
    default=None,
    help="Also reconstruct with this geometry on the same grid and write both side by side in one grey "
    "window (<scan>_<name>_vs_<geometry>.png).",
)
@click.option(
    "--export",
    "export",
    type=click.Choice(FORMATS),
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
    type=FiniteFloat(),
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
    compare_geometry: str | None,
    export: tuple[str, ...],
    out_dir: Path | None,
    max_minutes: float,
    yes: bool,
    scheduler: str | None,
    **values: Any,
) -> None:
    """Reconstruct SCAN (an orbitct scan file) and store the volume in it.

    The time it will take is estimated before anything large is allocated (from the projectors' speed on this
    machine now); above --max-minutes it asks on a terminal and refuses elsewhere, unless --yes. A calibrated
    geometry that failed its quality check is refused (exit 2) unless --accept-failed-geometry, which the volume
    then records; the verdict (passed, or passed with warnings) is printed last."""
    import sys

    from orbitct.scanfile import ScanFileError
    from recon import (
        FailedGeometryError,
        ReconError,
        ReconExistsError,
        TooLongError,
        compare_reconstructions,
        reconstruct_scan,
    )

    options = model_from(
        ReconstructionOptions, {**values, "max_minutes": None if yes else max_minutes}, flags={**FLAGS}
    )
    algorithm, geometry = options.algorithm, options.geometry
    cluster = _cluster(scheduler, options.mar)

    def run(opts: ReconstructionOptions) -> ReconResult:
        with ProgressBar() as bar:
            return reconstruct_scan(scan, opts, export=list(export), out_dir=out_dir, progress=bar, cluster=cluster)

    try:
        try:
            res = run(options)
        except TooLongError as exc:
            if not (sys.stdin.isatty() and click.confirm(f"{exc}. Start it anyway?", default=False, err=True)):
                raise Failure(
                    str(exc), "invalid_parameters", "--yes starts it anyway, --max-minutes M sets the limit"
                ) from None
            res = run(options.model_copy(update={"max_minutes": None}))
    except ReconExistsError as exc:
        raise Failure(str(exc), "conflict", "--overwrite replaces it, --name NAME keeps both") from None
    except FailedGeometryError as exc:
        fail(exc.what, "failed_quality_check", exc.advice("pass --accept-failed-geometry"))
    except (ReconError, ScanFileError) as exc:
        raise click.ClickException(str(exc)) from None
    nz, ny, nx = res.volume_shape
    click.echo(
        f"{res.path}: /recon/{res.name}  {algorithm} with {geometry} geometry, {nz}x{ny}x{nx} voxels of "
        f"{res.voxel_mm[0]:g} mm, {res.elapsed_s:.1f} s (estimated {res.params['estimated_s']:.1f} s)"
    )
    click.echo(f"  grid: {res.params['grid_choice']}")
    peak = res.params.get("device_peak_bytes")
    click.echo(f"  device: {res.params['device']}" + (f", {peak / 2**20:,.0f} MiB peak GPU memory" if peak else ""))
    if res.compile_s > 0.5 and peak:  # on a GPU
        click.echo(
            f"  {res.compile_s:.1f} s compiling numerical kernels (the GPU's are compiled in every run, the CPU's once "
            "after installation; not counted above)"
        )
    elif res.compile_s > 0.5:
        click.echo(
            f"  first use after installation: {res.compile_s:.1f} s compiling numerical kernels (cached for the next "
            "run; not counted above)"
        )
    if cluster is not None:
        click.echo(f"  views split across {res.params['cluster_workers']} Dask workers at {scheduler}")
    if res.cost:
        final = bool(res.params.get("final_cost"))
        last = "at the result" if final else "before the last iteration (--final-cost for the result's)"
        click.echo(f"  cost {res.cost[0]:.6g} at the start -> {res.cost[-1]:.6g} {last}")
    for p in res.exported:
        click.echo(f"  wrote {p}")
    click.echo(f"  verdict: {res.verdict.label}" + (" (warnings below)" if res.verdict.warnings else ""))
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
                options,
                geometry=compare_geometry,
                name=f"{res.name}_vs_{compare_geometry}",
                max_minutes=None,
                grid=res.grid,
                progress=bar,
                cluster=cluster,
            )
        base = out_dir if out_dir is not None else res.path.parent
        base.mkdir(parents=True, exist_ok=True)
        figure = compare_reconstructions(
            res.path, [res.name, other.name], base / f"{res.path.stem}_{res.name}_vs_{compare_geometry}.png"
        )
    except ReconExistsError as exc:
        raise Failure(str(exc), "conflict", "--overwrite replaces it") from None
    except FailedGeometryError as exc:
        fail(exc.what, "failed_quality_check", exc.advice("pass --accept-failed-geometry"))
    except (ReconError, ScanFileError) as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(
        f"  /recon/{other.name} with {compare_geometry} geometry, {other.elapsed_s:.1f} s; side by side: {figure}"
    )
    click.echo(f"  verdict: {other.verdict.label}" + (" (warnings below)" if other.verdict.warnings else ""))
    for w in other.warnings:
        click.echo(f"warning: {w}", err=True)


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
        raise Failure(
            f"cannot reach the Dask scheduler at {address} ({exc or 'no answer'})",
            "unavailable",
            "start it (dask scheduler), or give the address of a running one to --scheduler",
        ) from None
    if not client.scheduler_info()["workers"]:
        try:
            client.wait_for_workers(1, timeout=30)
        except Exception:  # noqa: BLE001
            client.close()
            raise Failure(
                f"the Dask scheduler at {address} has no workers (none joined within 30 s)",
                "unavailable",
                f"start one (dask worker {address}) and run it again",
            ) from None
    return client
