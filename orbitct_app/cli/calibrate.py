"""``orbitct calibrate``: geometric calibration of a scan file from the BBs in its projections."""

from __future__ import annotations

from pathlib import Path

import click

from orbitct_app.cli.failure import fail
from orbitct_app.cli.progress import ProgressBar
from orbitct_app.cli.values import FiniteFloat


@click.command()
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--method",
    type=click.Choice(["bundle", "paper"]),
    default="bundle",
    show_default=True,
    help="bundle: joint robust least squares; paper: the published alternation (Ma et al. 2022).",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write the results into a copy of SCAN at this path instead of into SCAN.",
)
@click.option(
    "--report",
    "report_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Directory for table1.md/.csv, rpe_violin.png and corrections.png.",
)
@click.option(
    "--iterations",
    type=click.IntRange(1, 200),
    default=None,
    help="paper: alternations (default 3); bundle: maximum LM iterations (default 30).",
)
@click.option(
    "--intrinsics",
    type=click.Choice(["fixed", "sdd", "sdd+pp"]),
    default="fixed",
    show_default=True,
    help="bundle: also estimate per view the source-detector distance and the piercing point.",
)
@click.option(
    "--diameter-mm",
    type=FiniteFloat(),
    default=None,
    help="BB diameter (default: /markers@diameter_mm, else estimated).",
)
@click.option(
    "--max-predicted-px",
    type=FiniteFloat(min=0.0, min_open=True),
    default=0.5,
    show_default=True,
    help="Quality check: the largest predicted field-of-view error a view may have.",
)
@click.option(
    "--bridge-max-views",
    type=click.IntRange(0, 1000),
    default=10,
    show_default=True,
    help="bundle: the widest run of views with fewer than 4 BBs that is bridged from its neighbours.",
)
@click.option(
    "--scale-bar-mm",
    type=FiniteFloat(min=0.0, min_open=True),
    default=None,
    help="Known distance between two BBs (a scale bar measured on the bench): sets the metric scale.",
)
@click.option(
    "--scale-bar-bbs",
    type=str,
    default=None,
    metavar="I,J",
    help="Which BBs span the scale bar (numbers as in the report); default: the one pair near its length.",
)
@click.option(
    "--accept-poor",
    is_flag=True,
    help="Exit 0 even when the quality check fails (the geometry is stored either way, marked failed).",
)
def calibrate(
    scan: Path,
    method: str,
    out: Path | None,
    report_dir: Path | None,
    iterations: int | None,
    intrinsics: str,
    diameter_mm: float | None,
    max_predicted_px: float,
    bridge_max_views: int,
    scale_bar_mm: float | None,
    scale_bar_bbs: str | None,
    accept_poor: bool,
) -> None:
    """Calibrate SCAN's geometry from the BBs on the object; writes /geometry/calibrated and /markers.

    Exit status: 0 calibrated and the quality check passed; 1 not calibrated (the message says why);
    3 calibrated but the quality check failed (views without a geometry, or a predicted error above
    --max-predicted-px): the geometry is stored, marked failed, and the reasons are printed."""
    import calib
    from orbitct.scanfile import ScanFileError

    options: dict[str, object] = {
        "intrinsics": intrinsics,
        "max_predicted_px": max_predicted_px,
        "bridge_max_views": bridge_max_views,
    }
    if iterations is not None:
        options["iterations"] = iterations
    if diameter_mm is not None:
        options["diameter_mm"] = diameter_mm
    if scale_bar_mm is not None:
        options["scale_bar_mm"] = scale_bar_mm
    if scale_bar_bbs is not None:
        options["scale_bar_bbs"] = _bb_pair(scale_bar_bbs)
    try:
        with ProgressBar() as bar:
            res = calib.calibrate_scan(scan, method=method, out=out, report_dir=report_dir, progress=bar, **options)
    except (calib.CalibrationError, ScanFileError) as exc:
        raise click.ClickException(str(exc)) from None
    last = res.iterations[-1]
    click.echo(
        f"{res.path}: {method}, {res.n_bbs} BBs in {res.n_frames} projections, {res.elapsed_s:.2f} s "
        f"({1000 * res.elapsed_s / max(res.n_frames, 1):.2f} ms/frame; detection {res.detect_s:.2f} s, "
        f"estimation {res.estimate_s:.2f} s)"
    )
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


def _bb_pair(text: str) -> tuple[int, int]:
    """``I,J`` -> two BB numbers, or a one-line usage error."""
    parts = text.replace(" ", "").split(",")
    if len(parts) != 2 or not all(p.isdigit() for p in parts):
        raise click.BadParameter(
            f"{text!r}: give two BB numbers as I,J (for example 2,7)", param_hint="--scale-bar-bbs"
        )
    return int(parts[0]), int(parts[1])
