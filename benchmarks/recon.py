"""Reconstruction benchmark: Joseph forward/back projection, FDK and PWLS against RTK's CPU filters.

Usage: .venv/bin/python benchmarks/recon.py [--large] [--pwls-iterations N] [--threads N] [--max-load L]
Prints the machine, a table of wall and CPU times, throughput ratios against RTK (measured in
the same run when itk-rtk is installed, otherwise the reference numbers from issue 6) and the
peak memory of each step (its input plus everything it allocates) relative to one float32
volume plus the float32 projections; then each kernel's share of the machine's arithmetic peak
and copy bandwidth, both measured in the same run. Ratios are not reported when the load average
at the start is above --max-load (other work on the cores makes them meaningless).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import psutil

# this file is named like the package it measures: keep its folder off the import path
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

from machine_info import cpu_model as cpu_name
from machine_info import machine_peaks

# Reference: RTK CPU filters on 2 cores, 128^3 voxels, 180 views of 128^2 (issue 6).
RTK_REFERENCE_S = {"forward": 0.8, "back": 2.1, "fdk": 1.7}
# What the share of the machine counts per unit of work: the interpolation's arithmetic and the taps it reads (the
# adjoint reads and writes its taps); ray set-up, index arithmetic and scratch are not counted, so the shares are
# lower bounds of what the kernels do. Units: forward/back per ray step, FDK per voxel and view it interpolates.
FLOPS_PER_UNIT = {"forward": 10, "back": 10, "fdk": 11}
BYTES_PER_UNIT = {"forward": 16, "back": 32, "fdk": 16}


def ray_steps_exact(grid, g) -> int:
    """Planes every ray of ``g`` steps through in ``grid`` (what the Joseph kernels loop over)."""
    import numba

    from recon.projector import _ray

    @numba.njit(parallel=True, cache=False)
    def count(rays, vox, nv, rows, cols, nx, ny, nz):  # type: ignore[no-untyped-def]
        total = np.zeros(nv, np.int64)
        for n in numba.prange(nv):
            for r in range(rows):
                for c in range(cols):
                    k_lo, k_hi = _ray(rays, vox, n, r, c, nx, ny, nz)[4:6]
                    total[n] += max(k_hi - k_lo + 1, 0)
        return total.sum()

    from recon.operator import index_rays

    nz, ny, nx = grid.shape
    vox = np.asarray(grid.voxel_mm, dtype=np.float64)
    return int(count(index_rays(grid, g), vox, g.n_views, g.panel.rows, g.panel.cols, nx, ny, nz))


def voxel_views_exact(grid, g) -> int:
    """Voxel-view pairs FDK's back-projector interpolates: per view, the voxels that land on the panel."""
    import numba

    from recon.operator import index_matrices
    from recon.projector import voxel_row_range

    @numba.njit(parallel=True, cache=False)
    def count(mats, nz, ny, nx, rows, cols):  # type: ignore[no-untyped-def]
        total = np.zeros(mats.shape[0], np.int64)
        for n in numba.prange(mats.shape[0]):
            for z in range(nz):
                for y in range(ny):
                    x0, x1 = voxel_row_range(mats[n], y, z, nx, rows, cols)
                    total[n] += max(x1 - x0 + 1, 0)
        return total.sum()

    nz, ny, nx = grid.shape
    return int(count(index_matrices(grid, g), nz, ny, nx, g.panel.rows, g.panel.cols))


def measure(fn: Callable[[], object], repeat: int, warm_up: bool = True) -> tuple[float, float, int]:
    """Best wall time, CPU time of that run, and peak bytes allocated during the runs (tracemalloc)."""
    if warm_up:
        fn()  # loads the cached numba kernels
    best = (float("inf"), 0.0)
    tracemalloc.start()
    for _ in range(repeat):
        tracemalloc.reset_peak()
        t, c = time.perf_counter(), time.process_time()
        fn()
        best = min(best, (time.perf_counter() - t, time.process_time() - c))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return best[0], best[1], peak


def rtk_times(n: int, size: int, views: int, g, repeat: int) -> dict[str, float] | None:
    """Best of ``repeat`` runs of the same cases with RTK's CPU filters, or None when itk-rtk is not installed."""
    try:
        import itk
        from itk import RTK as rtk
    except ImportError:
        return None
    from recon.export import rtk_parameters

    params, layout = rtk_parameters(g)
    geo = rtk.ThreeDCircularProjectionGeometry.New()
    for p in params:
        geo.AddProjection(
            p["SourceToIsocenterDistance"],
            p["SourceToDetectorDistance"],
            p["GantryAngle"],
            p["ProjectionOffsetX"],
            p["ProjectionOffsetY"],
            p["OutOfPlaneAngle"],
            p["InPlaneAngle"],
            p["SourceOffsetX"],
            p["SourceOffsetY"],
        )
    ImageType = itk.Image[itk.F, 3]
    vox = g.panel.pitch_col * float(np.median(g.sod() / g.sdd))

    sources = []  # the pipeline objects must outlive their output images (ITK frees them otherwise)

    def const(size3, spacing, origin):
        src = rtk.ConstantImageSource[ImageType].New()
        src.SetSize(size3)
        src.SetSpacing(spacing)
        src.SetOrigin(origin)
        src.SetConstant(1.0)  # non-zero data, as ours
        src.Update()
        sources.append(src)
        return src.GetOutput()

    vol = const([n] * 3, [vox] * 3, [-(n - 1) / 2 * vox] * 3)
    proj = const(
        [size, size, views],
        [g.panel.pitch_col, g.panel.pitch_row, 1.0],
        [layout["origin"][0], layout["origin"][1], 0.0],
    )
    out = {}
    fp = rtk.JosephForwardProjectionImageFilter[ImageType, ImageType].New()
    fp.SetInput(0, proj)
    fp.SetInput(1, vol)
    fp.SetGeometry(geo)
    bp = rtk.JosephBackProjectionImageFilter[ImageType, ImageType].New()
    bp.SetInput(0, vol)
    bp.SetInput(1, proj)
    bp.SetGeometry(geo)
    fdk = rtk.FDKConeBeamReconstructionFilter[ImageType].New()
    fdk.SetInput(0, vol)
    fdk.SetInput(1, proj)
    fdk.SetGeometry(geo)
    for key, flt in (("forward", fp), ("back", bp), ("fdk", fdk)):
        best = float("inf")
        for _ in range(repeat):
            flt.Modified()
            t = time.perf_counter()
            flt.Update()
            best = min(best, time.perf_counter() - t)
        out[key] = best
    return out


def run_case(
    n: int, size: int, views: int, repeat: int, pwls_iterations: int, peaks: tuple[float, float], ratios: bool
) -> None:
    from orbitct.geometry import ViewGeometry
    from orbitct.reference_bench import PANEL_MM, SAD_MM, SDD_MM, reference_panel
    from recon import VolumeGrid, fdk, projector

    det = reference_panel(size, PANEL_MM / size)
    g = ViewGeometry.from_carm(np.linspace(0, 2 * np.pi, views, endpoint=False), 0.0, SAD_MM, SDD_MM, det)
    vox = det.pitch_col * SAD_MM / SDD_MM
    grid = VolumeGrid.centered((n, n, n), vox)
    A = projector(grid, g)
    rng = np.random.default_rng(0)
    x = rng.random(grid.shape, dtype=np.float32)
    y = A(x)
    base = grid.nbytes + y.nbytes
    rows = []
    warm = n == 128
    # a fresh operator per call so that its scratch buffers count towards the peak memory
    t, c, m = measure(lambda: projector(grid, g)(x), repeat, warm)
    rows.append(("forward (Joseph)", t, c, x.nbytes + m, "forward"))
    t, c, m = measure(lambda: projector(grid, g).T(y), repeat, warm)
    rows.append(("back (matched Joseph)", t, c, y.nbytes + m, "back"))
    t, c, m = measure(lambda: fdk(y, grid, g, window="hann"), repeat, warm)
    rows.append(("FDK (filter + voxel BP)", t, c, y.nbytes + m, "fdk"))
    rtk = rtk_times(n, size, views, g, repeat)
    print(
        f"\ncase: {n}^3 voxels ({grid.nbytes / 2**20:.0f} MiB), {views} views of {size}^2 "
        f"({y.nbytes / 2**20:.0f} MiB); memory budget 1.5 x {base / 2**20:.0f} MiB"
    )
    import numba

    threads = numba.get_num_threads()
    print(
        f"{'step':26s} {'wall s':>8s} {'cpu s':>8s} {'RTK s':>8s} {'speed-up':>9s} {'cpu-based':>10s} {'peak MiB':>9s} {'/ (vol+proj)':>13s}"
    )
    for label, t, c, m, key in rows:
        ref = (rtk or {}).get(key, RTK_REFERENCE_S.get(key) if n == 128 else None)
        ratio = f"{ref / t:9.2f}" if ref and ratios else f"{'-':>9s}"
        ideal = f"{ref / (c / threads):10.2f}" if ref and ratios else f"{'-':>10s}"
        reft = f"{ref:8.2f}" if ref else f"{'-':>8s}"
        print(f"{label:26s} {t:8.3f} {c:8.3f} {reft} {ratio} {ideal} {m / 2**20:9.1f} {m / base:12.2f}x")
    print("speed-up = RTK s / wall s; cpu-based = RTK s / (cpu s / threads), the wall time on idle cores")
    print(
        "RTK column:",
        "measured in this run (itk-rtk)"
        if rtk
        else "itk-rtk not installed; reference numbers from issue 6 (2 cores, 128^3 only)",
    )
    steps = ray_steps_exact(grid, g)
    units = {"forward": steps, "back": steps, "fdk": voxel_views_exact(grid, g)}
    flops, copy = peaks
    print(
        f"share of the machine (measured in this run: {flops:.0f} GFLOP/s float32 matrix product, {copy:.1f} GB/s "
        "copy); counted per ray step (forward, back) or voxel and view (FDK): the interpolation's flops and the "
        "bytes of its taps, so the shares are lower bounds"
    )
    print(f"{'step':26s} {'units':>9s} {'GFLOP/s':>8s} {'% peak':>7s} {'tap GB/s':>9s} {'% copy':>7s}")
    for label, t, _, _, key in rows:
        gflops = units[key] * FLOPS_PER_UNIT[key] / t / 1e9
        gbs = units[key] * BYTES_PER_UNIT[key] / t / 1e9
        print(
            f"{label:26s} {units[key]:9.2e} {gflops:8.2f} {100 * gflops / flops:7.1f} {gbs:9.2f} "
            f"{100 * gbs / copy:7.1f}"
        )
    if pwls_iterations:
        run_pwls(grid, g, y, pwls_iterations, base)


def run_pwls(grid, g, y: np.ndarray, iterations: int, base: int) -> None:
    """PWLS/SPS with the projections streamed from an HDF5 file, as the scan pipeline can do."""
    import tempfile

    import h5py
    import numba

    from recon import projector, pwls_sps

    with tempfile.TemporaryDirectory() as tmp:
        with h5py.File(Path(tmp) / "projections.h5", "w") as f:
            f.create_dataset("y", data=y, chunks=(1,) + y.shape[1:])
        with h5py.File(Path(tmp) / "projections.h5", "r") as f:
            A = projector(grid, g)
            t0, c0 = time.perf_counter(), time.process_time()
            tracemalloc.start()
            # the start volume is allocated inside the window: it counts, and becomes the iterate
            res = pwls_sps(A, f["y"], None, iterations=iterations, x0=np.zeros(A.padded_shape, np.float32))
            peak = tracemalloc.get_traced_memory()[1]  # everything allocated; the projections stay in the file
            tracemalloc.stop()
            el, cpu = time.perf_counter() - t0, time.process_time() - c0
    per_it, per_it_idle = el / iterations, cpu / numba.get_num_threads() / iterations
    print(
        f"PWLS/SPS {iterations} iterations (projections streamed from HDF5, 8 views per chunk): wall {el:.1f} s "
        f"({per_it:.2f} s/iteration, set-up and final cost included), cpu {cpu:.1f} s (idle-core estimate "
        f"{per_it_idle:.2f} s/iteration); 50 iterations: wall {50 * per_it:.0f} s, idle-core estimate "
        f"{50 * per_it_idle:.0f} s (target < 60 s); cost {res.cost[0]:.4g} -> {res.cost[-1]:.4g}; "
        f"peak {peak / 2**20:.1f} MiB = {peak / base:.2f} x (vol+proj) (target <= 1.5 x)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--large", action="store_true", help="also run 256^3 voxels, 500 views of 384^2")
    ap.add_argument("--pwls-iterations", type=int, default=50, help="PWLS iterations on the 128^3 case (0 skips)")
    ap.add_argument("--repeat", type=int, default=5, help="timed runs per step; the best is reported")
    ap.add_argument("--threads", type=int, default=None, help="numba threads (default: all cores)")
    ap.add_argument(
        "--max-load", type=float, default=1.5, help="no RTK ratio is reported above this load average at the start"
    )
    args = ap.parse_args()
    load = os.getloadavg()[0]  # before this run's own work raises it
    import numba

    if args.threads:
        numba.set_num_threads(args.threads)
    print(
        f"machine: {cpu_name()}, {psutil.cpu_count(logical=False)} cores / {os.cpu_count()} threads, "
        f"{psutil.virtual_memory().total / 2**30:.0f} GiB; numba threads {numba.get_num_threads()}; "
        f"load average {load:.2f} at start (shared machines inflate wall times)"
    )
    ratios = load <= args.max_load
    if not ratios:
        print(
            f"the load average at the start ({load:.2f}) is above {args.max_load}: other work shares the cores, so "
            "the times are printed but no ratio to RTK is reported"
        )
    peaks = machine_peaks()
    run_case(128, 128, 180, args.repeat, args.pwls_iterations, peaks, ratios)
    if args.large:
        run_case(256, 384, 500, 1, 0, peaks, ratios)


if __name__ == "__main__":
    main()
