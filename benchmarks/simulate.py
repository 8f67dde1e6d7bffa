"""Benchmark: simulate experiment A (default 500 frames of 768 x 768) and report frames per second.

Target (issue 2): at least 25 frames/s on 2 cores. Smaller runs for a quick check:
    python benchmarks/simulate.py --frames 50 --detector-size 256
With the polychromatic beam (each material projected apart, then summed over the spectrum):
    python benchmarks/simulate.py --beam polychromatic --frames 100
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

# scripts here share names with the packages they measure: the project root goes before this folder
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

import numba
import numpy as np
from machine_info import cpu_model

from orbitct.phantoms import experiment_phantom
from orbitct.simulator import Beam, SimulatedBench, line_integrals, simulate_scan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--experiment", default="A", choices=["A", "B", "C"])
    ap.add_argument("--orbit", default=None, help="orbit kind (default: the experiment's)")
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--detector-size", type=int, default=768)
    ap.add_argument("--errors", default="bench", choices=["bench", "none"])
    ap.add_argument("--beam", default="mono", choices=["mono", "polychromatic"])
    ap.add_argument("--threads", type=int, default=None, help="numba threads (default: all cores)")
    ap.add_argument("--keep", type=Path, default=None, help="write the scan here instead of a temporary file")
    args = ap.parse_args()
    if args.threads:
        numba.set_num_threads(args.threads)

    bench = SimulatedBench.with_panel(args.detector_size, beam=Beam.preset(args.beam))
    phantom = experiment_phantom(args.experiment)
    # compile every kernel before timing
    li = line_integrals(phantom, bench.lab_view, 0, beam=bench.beam)
    bench.model.expose(li, np.random.default_rng(0))

    # stage timings on a few frames
    n_stage = min(20, args.frames)
    rng = np.random.default_rng(1)
    t = time.perf_counter()
    for _ in range(n_stage):
        li = line_integrals(phantom, bench.lab_view, 0, beam=bench.beam)
    t_li = (time.perf_counter() - t) / n_stage
    t = time.perf_counter()
    for _ in range(n_stage):
        bench.model.expose(li, rng)
    t_exp = (time.perf_counter() - t) / n_stage

    with tempfile.TemporaryDirectory() as tmp:
        out = args.keep or Path(tmp) / "bench.h5"
        cpu0 = time.process_time()
        res = simulate_scan(
            args.experiment,
            args.orbit,
            out=out,
            n_frames=args.frames,
            detector_px=args.detector_size,
            errors=args.errors,
            seed=0,
            n_dark=10,
            n_flat=10,
            bench=bench,
            overwrite=True,
        )
        cpu_s = time.process_time() - cpu0
        size_mb = os.path.getsize(out) / 1e6

    fps = res.n_frames / res.elapsed_s
    cores = min(2, numba.get_num_threads())
    cpu_per_frame = cpu_s / res.n_frames
    rows = [
        ("experiment / orbit", f"{args.experiment} / {res.orbit.name}"),
        ("frames (proj + 10 dark + 10 flat)", f"{res.n_frames}"),
        ("detector", f"{args.detector_size} x {args.detector_size} px"),
        ("primitives", f"{len(phantom.primitives)}"),
        (
            "beam",
            "one energy"
            if bench.beam is None
            else f"{bench.beam.kv:g} kV spectrum, {len(phantom.by_material)} materials",
        ),
        ("line integrals per frame", f"{t_li * 1e3:.1f} ms"),
        ("detector model per frame", f"{t_exp * 1e3:.1f} ms"),
        ("whole scan (incl. HDF5 write)", f"{res.elapsed_s:.2f} s"),
        ("frames per second (wall clock)", f"{fps:.1f}  (target >= 25 on 2 cores)"),
        ("CPU time per frame (all threads)", f"{cpu_per_frame * 1e3:.1f} ms"),
        (
            f"frames/s if {cores} cores were free",
            f"{cores / cpu_per_frame:.1f}  (CPU time / cores; other load excluded)",
        ),
        ("file size", f"{size_mb:.0f} MB"),
    ]
    w = max(len(k) for k, _ in rows)
    print("orbitct simulate benchmark")
    print(
        f"machine: {cpu_model()}, {os.cpu_count()} cores, numba threads {numba.get_num_threads()}, "
        f"load avg {os.getloadavg()[0]:.1f}"
    )
    print("-" * (w + 40))
    for k, v in rows:
        print(f"{k:<{w}}  {v}")


if __name__ == "__main__":
    main()
