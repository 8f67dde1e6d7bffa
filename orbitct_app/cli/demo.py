"""``orbitct demo``: the paper's experiment A on the simulated bench, end to end (scan, calibrate, reconstruct)."""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path
from typing import Any

import click

from orbitct_app.cli.failure import fail
from orbitct_app.cli.progress import ProgressBar
from orbitct_app.cli.values import SEED, FiniteFloat

DEFAULT_CONFIG = Path("config/bench.yaml")


def _step(title: str) -> None:
    click.echo(click.style(f"\n== {title}", bold=True))


def _truth_error(scan_path: Path) -> None:
    """Print how far the nominal and calibrated geometries are from the twins' truth (after similarity alignment)."""
    from calib.evaluate import similarity_aligned_error_px as error_px
    from orbitct.scanfile import ScanFile

    with ScanFile(scan_path) as sf:
        if not (sf.has_geometry("truth") and sf.has_geometry("calibrated")):
            return
        proj = sf.projection_indices
        truth = sf.geometry("truth")[proj]
        nominal = error_px(sf.geometry("nominal")[proj], truth)[0]
        calibrated = error_px(sf.geometry("calibrated")[proj], truth)[0]
    click.echo(
        f"   geometry error against the twins' truth: nominal {nominal:.2f} px -> calibrated {calibrated:.3f} px RMS"
    )


def _reconstruct(
    scan_path: Path,
    out_dir: Path,
    algorithm: str,
    geometry: str,
    iterations: int,
    voxels: int,
    voxel_mm: float | None = None,
) -> Any:
    """One reconstruction with PNG slices (a failure is reported and the demo goes on); its result or None."""
    from recon import ReconError, reconstruct_scan

    kwargs: dict[str, Any] = dict(
        algorithm=algorithm,
        geometry=geometry,
        shape=(voxels, voxels, voxels),
        voxel_mm=voxel_mm,
        export="png",
        out_dir=out_dir / "recon",
    )
    if iterations:
        kwargs["iterations"] = iterations
    try:
        with ProgressBar() as bar:
            rr = reconstruct_scan(scan_path, progress=bar, **kwargs)
    except ReconError as exc:
        click.echo(f"   {algorithm} / {geometry} failed: {exc}")
        return None
    click.echo(
        f"   {algorithm} / {geometry}: {rr.volume_shape} in {rr.elapsed_s:.1f} s -> /recon/{rr.name}; "
        f"slices: {', '.join(str(p) for p in rr.exported[:3])}"
    )
    return rr


@click.command()
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("demo-output"),
    show_default=True,
    help="Folder for the scan file, calibration report and reconstruction slices.",
)
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Bench configuration (default: config/bench.yaml if present, else built-in defaults).",
)
@click.option("--frames", type=click.IntRange(10, 2000), default=240, show_default=True, help="Projections.")
@click.option("--size", type=click.IntRange(32, 1024), default=256, show_default=True, help="Detector pixels (square).")
@click.option(
    "--voxels", type=click.IntRange(16, 512), default=96, show_default=True, help="Reconstruction grid (cube)."
)
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the bench error profile.")
@click.option(
    "--tilt-deg",
    type=FiniteFloat(1, 25),
    default=20.0,
    show_default=True,
    help="Sawtooth tilt amplitude (the paper's experiment A: 20).",
)
@click.option(
    "--pwls-iterations",
    type=click.IntRange(0, 200),
    default=0,
    show_default=True,
    help="Also run PWLS with this many iterations (0: FDK only, faster).",
)
@click.option(
    "--time-scale",
    type=FiniteFloat(1, 1000),
    default=25.0,
    show_default=True,
    help="The twins move this many times faster than the real bench (1 = real time).",
)
@click.option("--skip-calibration", is_flag=True, help="Stop after the scan.")
def demo(
    out_dir: Path,
    config_path: Path | None,
    frames: int,
    size: int,
    voxels: int,
    seed: int,
    tilt_deg: float,
    pwls_iterations: int,
    time_scale: float,
    skip_calibration: bool,
) -> None:
    """Experiment A on the simulated bench: twins, sawtooth scan with the bench errors, calibration, reconstruction."""
    from acquire.config import BenchConfig, load_config
    from acquire.errors import AcquireError
    from acquire.runner import ScanRequest, run_scan

    t_start = time.monotonic()
    out_dir.mkdir(parents=True, exist_ok=True)
    scan_path = out_dir / "experiment-a.h5"
    if config_path is None and DEFAULT_CONFIG.is_file():
        config_path = DEFAULT_CONFIG
    try:
        config = load_config(config_path) if config_path is not None else BenchConfig()
    except AcquireError as exc:
        fail(str(exc))
    if not isinstance(config, BenchConfig):
        fail(f"{config_path} is a {config.kind} configuration", advice="give the demo a bench configuration")
    config = config.model_copy(update={"sim": config.sim.model_copy(update={"time_scale": time_scale})})

    _step(
        f"1/3 scan: sawtooth +-{tilt_deg:g} deg, {frames} frames at {size}x{size} px, bench error profile "
        f"(seed {seed}), twins in-process"
    )
    req = ScanRequest(
        config=config,
        out=scan_path,
        orbit="sawtooth",
        frames=frames,
        orbit_params={"amplitude_deg": tilt_deg},
        errors="bench",
        seed=seed,
        mode="step",
        sim=True,
        detector_size=size,
        overwrite=True,
    )
    try:
        with ProgressBar() as bar:
            res = run_scan(req, progress=bar)
    except AcquireError as exc:
        fail(f"scan refused: {exc}", "action_failed")
    click.echo(f"   {res.status}: {res.n_frames} frames in {res.elapsed_s:.1f} s -> {res.path}")
    if res.status != "complete":
        fail(f"the demo's scan is {res.status}: {res.reason}", "action_failed")
    if skip_calibration:
        return

    _step("2/3 calibration from the BBs on the object (bundle adjustment)")
    from calib import CalibrationError, calibrate_scan

    geometry = "nominal"
    cal = None
    try:
        with ProgressBar() as bar:
            cal = calibrate_scan(scan_path, method="bundle", report_dir=out_dir / "calibration", progress=bar)
    except CalibrationError as exc:
        click.echo(f"   calibration failed: {exc}; reconstructing with the nominal geometry")
    if cal is not None:
        click.echo(f"   {cal.n_bbs} BBs in {cal.n_frames} frames, {cal.elapsed_s:.1f} s")
        if cal.iterations:
            click.echo(
                f"   RPE: nominal {cal.iterations[0].rpe_mean_mm:.3f} mm -> calibrated {cal.iterations[-1].rpe_mean_mm:.3f} mm "
                f"(reprojection RMS {cal.reproj_rms_px:.3f} px)"
            )
        q = cal.quality
        if q is not None:
            click.echo(f"   {q.line()}")
            click.echo(f"   verdict: {q.label}")
        for w in cal.warnings[:5]:
            click.echo(f"   warning: {w}")
        _truth_error(scan_path)
        click.echo(f"   report (table, violin plots): {out_dir / 'calibration'}")
        if q is not None and not q.passed:
            click.echo(
                "   QUALITY CHECK FAILED: " + "; ".join(q.reasons) + "; reconstructing with the nominal geometry"
            )
        else:
            geometry = "calibrated"

    _step(f"3/3 reconstruction ({voxels}^3 voxels) with the {geometry} and the nominal geometry")
    runs = [("fdk", geometry, 0), ("fdk", "nominal", 0)] if geometry != "nominal" else [("fdk", "nominal", 0)]
    if pwls_iterations > 0:
        runs.insert(1, ("pwls", geometry, pwls_iterations))
    first = None
    for algorithm, geo, iters in runs:  # every volume on the grid of the first, so that they compare voxel by voxel
        rr = _reconstruct(scan_path, out_dir, algorithm, geo, iters, voxels, first.voxel_mm[0] if first else None)
        first = first or rr
    if geometry == "calibrated":
        from recon import ReconError, compare_reconstructions

        try:
            figure = compare_reconstructions(
                scan_path, ["fdk_calibrated", "fdk_nominal"], out_dir / "recon" / "comparison.png"
            )
            click.echo(f"   calibrated next to nominal, one grey window: {figure}")
        except ReconError as exc:
            click.echo(f"   no comparison figure: {exc}")

    click.echo(
        f"\ndone in {time.monotonic() - t_start:.0f} s. Scan file (frames, geometry, calibration, volumes): {scan_path}"
    )
    cmd = _orbitct_command()
    click.echo(f"inspect it with: {cmd} inspect {scan_path}")
    if cmd != "orbitct":
        click.echo(
            f"(orbitct is not on your PATH: run `source {Path(cmd).parent}/activate` once per terminal "
            f"to type plain `orbitct`, or call {cmd})"
        )


def _orbitct_command() -> str:
    """How the user can call this very ``orbitct``: plain when it is on the PATH, else its path (e.g. ``.venv/bin/orbitct``)."""
    here = Path(sys.executable).parent / "orbitct"
    found = shutil.which("orbitct")
    if found is not None and Path(found).resolve() == here.resolve():
        return "orbitct"
    try:
        return str(here.relative_to(Path.cwd()))
    except ValueError:
        return str(here)
