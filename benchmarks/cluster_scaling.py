"""Benchmark: a reconstruction split across the workers of a Dask cluster (1 and 2 worker processes on this machine).

Experiment A (500 frames of 768 x 768, simulated once and cached), FDK (or FDK then accelerated PWLS) at 0.5 mm on
the object-fitted grid: one process without Dask, then a local Dask cluster of 1 and of 2 worker processes (one
thread each). Prints wall time, speed-up, the per-view cost, the bytes the volumes move, the largest difference
from the single-process volume, and an estimate (stated as such) for 8 and 32 workers from those measurements.

    python benchmarks/cluster_scaling.py                   # FDK, 768 px, 500 frames
    python benchmarks/cluster_scaling.py --algorithm pwls --passes 2
    python benchmarks/cluster_scaling.py --size 384 --frames 250
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

import numpy as np
from machine_info import describe_machine

#: network the 8- and 32-worker estimate assumes (10 GbE, about 1.1 GB/s of payload)
NETWORK_BYTES_S = 1.1e9


def _scan(cache: Path, size: int, frames: int) -> Path:
    from orbitct.simulator.scan import simulate_scan

    path = cache / f"A_{size}_{frames}.h5"
    if not path.exists():
        simulate_scan("A", out=path, n_frames=frames, detector_px=size)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=768, help="detector pixels per side")
    ap.add_argument("--frames", type=int, default=500, help="projections")
    ap.add_argument("--voxel-mm", type=float, default=0.5)
    ap.add_argument(
        "--algorithm",
        choices=["fdk", "pwls"],
        default="fdk",
        help="fdk, or pwls: FDK then --passes passes of ordered subsets with momentum",
    )
    ap.add_argument("--passes", type=int, default=2, help="PWLS passes")
    ap.add_argument("--subsets", type=int, default=12, help="PWLS ordered subsets")
    ap.add_argument("--cache", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "orbitct-cluster-bench")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    from distributed import Client, LocalCluster

    import recon
    from recon.cluster import PARTS_PER_WORKER

    pwls = args.algorithm == "pwls"
    what = f"FDK, then PWLS: {args.passes} passes of {args.subsets} ordered subsets with momentum," if pwls else "FDK"
    print(describe_machine())
    print(
        f"experiment A, {args.size} px, {args.frames} frames, {what} at {args.voxel_mm:g} mm on the object-fitted "
        f"grid (true geometry); 1-min load at start {os.getloadavg()[0]:.2f}\n"
    )
    scan = _scan(args.cache, args.size, args.frames)
    options: dict[str, object] = {"algorithm": args.algorithm, "geometry": "truth"}
    if pwls:
        options.update(iterations=args.passes, subsets=args.subsets, momentum=True)
    with tempfile.TemporaryDirectory(dir=args.cache) as work:
        copy = Path(work) / "scan.h5"
        shutil.copyfile(scan, copy)
        first = recon.reconstruct_scan(copy, algorithm="fdk", geometry="truth", voxel_mm=args.voxel_mm, name="ref")
        grid = first.grid  # found once (a coarse FDK), then given to every run
        t = time.perf_counter()
        single = recon.reconstruct_scan(copy, grid=grid, name="single", **options)
        t_single = time.perf_counter() - t
        vol_bytes = int(np.prod(grid.shape)) * 4
        padded_bytes = 4 * int(np.prod([n + 2 for n in grid.shape]))
        rows = [("one process, no Dask", 1, t_single, 0, 0.0)]
        for n in (1, 2):
            with (
                LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address="127.0.0.1:0",
                    host="127.0.0.1",
                    memory_limit=0,
                ) as cluster,
                Client(cluster, set_as_default=False) as c,
            ):
                c.wait_for_workers(n)
                t = time.perf_counter()
                res = recon.reconstruct_scan(copy, grid=grid, name=f"dask{n}", cluster=c, **options)
                elapsed = time.perf_counter() - t
            moved = min(args.frames, PARTS_PER_WORKER * n) * vol_bytes  # FDK: one volume per part
            if pwls:  # each round: the iterate to every worker, one volume per worker summed and fetched
                moved += (1 + (args.passes + 1) * args.subsets) * 2 * n * padded_bytes
            diff = float(np.abs(res.volume - single.volume).max() / np.abs(single.volume).max())
            rows.append((f"Dask, {n} worker process(es)", n, elapsed, moved, diff))
    print(
        f"grid {grid.shape} voxels of {args.voxel_mm:g} mm ({vol_bytes / 1e6:.0f} MB float32): {first.params['grid_choice']}\n"
    )
    print("| run | workers | wall s | speed-up vs one process | volumes moved MB (counted) | max difference (rel.) |")
    print("|---|---|---|---|---|---|")
    for name, n, s, moved, diff in rows:
        print(f"| {name} | {n} | {s:.1f} | {t_single / s:.2f} | {moved / 1e6:.0f} | {diff:.1e} |")
    per_view = t_single / args.frames  # one process uses every core of this machine (the projectors are threaded)
    overhead = max(rows[1][2] - t_single, 0.0)  # Dask's own cost: the parts' volumes, the transfer, the gather
    rounds = 1 + (args.passes + 1) * args.subsets if pwls else 0
    print(
        f"\nper-view cost of this machine {1e3 * per_view:.0f} ms (one process, all cores); Dask's own cost with one "
        f"worker {overhead:.1f} s" + (f" over {rounds} PWLS rounds" if pwls else "")
    )
    print(
        f"\nEstimate (not measured): W workers on W machines like this one, {NETWORK_BYTES_S / 1e9:.1f} GB/s network, "
        "partial volumes summed pairwise (each level's transfers side by side)"
        + (", the iterate sent to each worker in turn every PWLS round" if pwls else "")
        + ", Dask's own cost as measured:\n"
    )
    print("| workers | views s | volumes moving s | time-to-image s |\n|---|---|---|---|")
    for w in (1, 2, 8, 32):
        levels = math.ceil(math.log2(max(2, 2 * w)))
        t_views = per_view * args.frames / w
        t_sum = levels * vol_bytes / NETWORK_BYTES_S
        if pwls:
            t_sum += rounds * (w + math.ceil(math.log2(max(2, w))) + 1) * padded_bytes / NETWORK_BYTES_S
        print(f"| {w} | {t_views:.1f} | {t_sum:.1f} | {t_views + t_sum + overhead:.1f} |")
    print(f"\n1-min load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
