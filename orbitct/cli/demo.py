"""``orbitct demo``: the paper's experiment A on the simulated bench, end to end (scan, calibrate, reconstruct)."""

from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path
from typing import Any

import click

from orbitct.cli.progress import ProgressBar

DEFAULT_CONFIG = Path("config/bench.yaml")


def _step(title: str) -> None:
    click.echo(click.style(f"\n== {title}", bold=True))


def _optional(module: str, attr: str) -> Any | None:
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        click.echo(f"   skipped: {module}.{attr} is not available in this installation ({exc})")
        return None


@click.command()
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=Path("demo-output"),
              show_default=True, help="Folder for the scan file, calibration report and reconstruction slices.")
@click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Bench configuration (default: config/bench.yaml if present, else built-in defaults).")
@click.option("--frames", type=click.IntRange(10, 2000), default=240, show_default=True, help="Projections.")
@click.option("--size", type=click.IntRange(32, 1024), default=256, show_default=True, help="Detector pixels (square).")
@click.option("--voxels", type=click.IntRange(16, 512), default=96, show_default=True, help="Reconstruction grid (cube).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the bench error profile.")
@click.option("--pwls-iterations", type=click.IntRange(0, 200), default=0, show_default=True,
              help="Also run PWLS with this many iterations (0: FDK only, faster).")
@click.option("--skip-calibration", is_flag=True, help="Stop after the scan.")
def demo(out_dir: Path, config_path: Path | None, frames: int, size: int, voxels: int, seed: int,
         pwls_iterations: int, skip_calibration: bool) -> None:
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
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    if not isinstance(config, BenchConfig):
        click.echo(f"error: {config_path} is a {config.kind} configuration; the demo needs a bench", err=True)
        sys.exit(2)

    _step(f"1/3 scan: sawtooth, {frames} frames at {size}x{size} px, bench error profile (seed {seed}), twins in-process")
    req = ScanRequest(config=config, out=scan_path, orbit="sawtooth", frames=frames, errors="bench", seed=seed,
                      mode="step", sim=True, detector_size=size, overwrite=True)
    try:
        with ProgressBar() as bar:
            res = run_scan(req, progress=bar)
    except AcquireError as exc:
        click.echo(f"error: scan refused: {exc}", err=True)
        sys.exit(1)
    click.echo(f"   {res.status}: {res.n_frames} frames in {res.elapsed_s:.1f} s -> {res.path}")
    if res.status != "complete":
        click.echo(f"   reason: {res.reason}", err=True)
        sys.exit(1)
    if skip_calibration:
        return

    _step("2/3 calibration from the BBs on the object (bundle adjustment)")
    calibrate_scan = _optional("calib", "calibrate_scan")
    geometry = "nominal"
    if calibrate_scan is not None:
        with ProgressBar() as bar:
            cal = calibrate_scan(scan_path, method="bundle", report_dir=out_dir / "calibration", progress=bar)
        last = cal.iterations[-1] if cal.iterations else None
        click.echo(f"   {cal.n_bbs} BBs in {cal.n_frames} frames, {cal.elapsed_s:.1f} s")
        if cal.iterations:
            click.echo(f"   RPE: nominal {cal.iterations[0].rpe_mean_mm:.3f} mm -> calibrated {last.rpe_mean_mm:.3f} mm "
                       f"(reprojection RMS {cal.reproj_rms_px:.3f} px)")
        for w in cal.warnings[:5]:
            click.echo(f"   warning: {w}")
        click.echo(f"   report (table, violin plots): {out_dir / 'calibration'}")
        geometry = "calibrated"

    _step(f"3/3 reconstruction ({voxels}^3 voxels) with the {geometry} and the nominal geometry")
    reconstruct_scan = _optional("recon", "reconstruct_scan")
    if reconstruct_scan is not None:
        runs = [("fdk", geometry, 0), ("fdk", "nominal", 0)] if geometry != "nominal" else [("fdk", "nominal", 0)]
        if pwls_iterations > 0:
            runs.insert(1, ("pwls", geometry, pwls_iterations))
        for algorithm, geo, iters in runs:
            with ProgressBar() as bar:
                kwargs: dict[str, Any] = dict(algorithm=algorithm, geometry=geo, shape=(voxels, voxels, voxels),
                                              export="png", out_dir=out_dir / "recon", progress=bar)
                if iters:
                    kwargs["iterations"] = iters
                rr = reconstruct_scan(scan_path, **kwargs)
            click.echo(f"   {algorithm} / {geo}: {rr.volume_shape} in {rr.elapsed_s:.1f} s -> /recon/{rr.name}; "
                       f"slices: {', '.join(str(p) for p in rr.exported[:3])}")

    click.echo(f"\ndone in {time.monotonic() - t_start:.0f} s. Scan file (frames, geometry, calibration, volumes): {scan_path}")
    click.echo(f"inspect it with: orbitct inspect {scan_path}")
