"""``orbitct warmup``: compile the numerical kernels once after installation, so no run pays for it later."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import click


@click.command()
def warmup() -> None:
    """Compile orbitct's numerical kernels now (numba; cached on disk afterwards).

    Runs a tiny simulated scan, its calibration and FDK and PWLS reconstructions; `make demo` and `make test`
    run it once after installing, so that the first real calibration or reconstruction does not spend tens
    of seconds compiling. Running it again costs a few seconds."""
    import calib
    import recon
    from orbitct.compiletime import CompileClock
    from orbitct.errorprofiles import make_profile
    from orbitct.simulator.scan import simulate_scan

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, CompileClock() as clock:
        scan = Path(tmp) / "warmup.h5"
        simulate_scan("A", out=scan, n_frames=60, detector_px=128, errors=make_profile("bench", 0, angle_scale=0.12))
        calib.calibrate_scan(scan, bridge_max_views=60, max_predicted_px=100.0)
        recon.reconstruct_scan(scan, algorithm="fdk", geometry="calibrated", shape=(16, 16, 16), voxel_mm=8.0)
        recon.reconstruct_scan(
            scan,
            algorithm="pwls",
            geometry="calibrated",
            shape=(16, 16, 16),
            voxel_mm=8.0,
            iterations=2,
            name="warmup_pwls",
        )
    click.echo(f"numerical kernels ready: {clock.seconds:.1f} s compiling, {time.perf_counter() - t0:.1f} s in all")
