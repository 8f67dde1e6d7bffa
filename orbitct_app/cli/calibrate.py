"""``orbitct calibrate``: geometric calibration of a scan file from the BBs in its projections."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from calib.options import CalibrationOptions
from orbitct_app.cli.failure import fail
from orbitct_app.cli.model_options import model_from, options_from
from orbitct_app.cli.progress import ProgressBar


@click.command()
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write the results into a new scan file at this path that reads its frames from SCAN (nothing copied; keep the two files together), leaving SCAN unchanged.",
)
@click.option(
    "--report",
    "report_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Directory for table1.md/.csv, rpe_violin.png, corrections.png and worst_view.png.",
)
@options_from(CalibrationOptions, metavars={"scale_bar_bbs": "I,J"})
@click.option(
    "--accept-poor",
    is_flag=True,
    help="Exit 0 even when the quality check fails (the geometry is stored either way, marked failed).",
)
def calibrate(scan: Path, out: Path | None, report_dir: Path | None, accept_poor: bool, **given: Any) -> None:
    """Calibrate SCAN's geometry from the BBs on the object; writes /geometry/calibrated and /markers.

    Exit status: 0 calibrated and the quality check passed; 1 not calibrated (the message says why);
    3 calibrated but the quality check failed (views without a geometry, or a predicted error above
    --max-predicted-px): the geometry is stored, marked failed, and the reasons are printed."""
    import calib
    from orbitct.scanfile import ScanFileError

    chosen = model_from(CalibrationOptions, given)
    method = chosen.method
    options = chosen.model_dump(exclude={"method"}, exclude_unset=True)
    try:
        with ProgressBar() as bar:
            res = calib.calibrate_scan(scan, method=method, out=out, report_dir=report_dir, progress=bar, **options)
    except (calib.CalibrationError, ScanFileError) as exc:
        raise click.ClickException(str(exc)) from None
    last = res.iterations[-1]
    click.echo(
        f"{res.path}: {method}, {res.n_bbs} BBs in {res.n_frames} projections, {res.elapsed_s:.2f} s "
        f"({1000 * res.elapsed_s / max(res.n_frames, 1):.2f} ms/frame)"
    )
    click.echo(f"time: {res.timing_line()}")
    if res.compile_s > 0.5:
        click.echo(
            f"first use after installation: {res.compile_s:.1f} s compiling numerical kernels (cached for the "
            "next run; not counted above)"
        )
    click.echo(
        f"RPE mean {last.rpe_mean_mm:.4f} mm, median {last.rpe_median_mm:.4f} mm, std {last.rpe_std_mm:.4f} mm; "
        f"reprojection RMS {res.reproj_rms_px:.3f} px (initial RPE mean {res.iterations[0].rpe_mean_mm:.3f} mm)"
    )
    q = res.quality
    if q is not None:
        click.echo(q.line())
        click.echo(f"verdict: {q.label}" + (" (warnings below)" if q.passed and q.warnings else ""))
    click.echo(res.scale_line())
    for w in res.warnings:
        click.echo(f"warning: {w}", err=True)
    if report_dir is not None:
        click.echo(f"report written to {report_dir}")
    if q is not None and not q.passed:
        what = "QUALITY CHECK FAILED: " + "; ".join(q.reasons)
        advice = (
            "the geometry is stored, marked quality=failed; read 'When a calibration fails its quality check' in the "
            "documentation (docs/explanation/calibration.md) and calibrate again"
        )
        if accept_poor:
            click.echo(f"warning: {what} (--accept-poor: exit 0 anyway); {advice}", err=True)
        else:
            fail(what, "failed_quality_check", advice + " (--accept-poor exits 0 anyway)")
