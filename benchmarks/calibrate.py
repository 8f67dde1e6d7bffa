"""Benchmark: calibrate simulated experiments A, B, C (768 x 768; 500, 656, 857 frames) with `bundle` and
`paper`, next to the paper's Table 1.

Per run (each in a fresh process, so peak RSS is its own): detection, identification and estimation time,
ms per frame, RPE statistics, reprojection RMS, geometry error against the truth after the best similarity
alignment (RMS px over points filling the FOV), peak memory (tracemalloc and RSS). Reference: the same
bundle solver fed the true BB projections plus Gaussian noise of the detector's measured centroid noise.

Targets for `bundle` (issue 5): whole calibration < 0.006 s/frame on 2 cores; geometry error <= 2x the
reference; peak memory < 1 GB for 857 frames. Simulated scans are cached (default: $TMPDIR/orbitct-calib-bench).
Each run calibrates a fresh copy of the scan that has been read once (in the page cache, as right after an
acquisition) and with numba's compiled kernels loaded; the time is the calibration only.

    python benchmarks/calibrate.py                       # full size, all three (simulating takes minutes)
    python benchmarks/calibrate.py --size 256 --frames-scale 0.25 --experiments A
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import queue
import shutil
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path
from typing import Any

# scripts here share names with the packages they measure: the project root goes before this folder
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

import numpy as np
from machine_info import cpu_model

PAPER_FRAMES = {"A": 500, "B": 656, "C": 857}


def cached_scan(cache: Path, experiment: str, size: int, frames: int, seed: int) -> Path:
    """Simulate (once) and return the scan of one experiment."""
    from orbitct.simulator.scan import simulate_scan

    path = cache / f"{experiment}_{size}_{frames}_seed{seed}.h5"
    if not path.exists():
        part = path.with_suffix(".h5.part")
        t = time.perf_counter()
        simulate_scan(experiment, out=part, n_frames=frames, detector_px=size, seed=seed, overwrite=True)
        os.replace(part, path)
        print(f"  simulated {path.name} in {time.perf_counter() - t:.0f} s", flush=True)
    return path


def _run(scan: str, method: str, work: str, queue: Any, trace: bool) -> None:
    """Child process: one calibration, its accuracy against the truth and its peak memory."""
    import psutil

    import calib
    from calib.evaluate import similarity_aligned_error_px, truth_fed_error_px
    from orbitct.scanfile import ScanFile

    out = Path(work) / f"{method}.h5"
    shutil.copyfile(scan, out)
    _warm_page_cache(out)
    # warm numba's cache outside the timing (a first call loads the compiled kernels)
    from calib.detect import FrameDetector, settings_for
    from calib.track import _predict_from_rays, match_frame

    FrameDetector(
        np.zeros((64, 64), np.float32), np.full((64, 64), 1e4, np.float32), settings_for(6.0, (64, 64))
    ).candidates(np.full((64, 64), 5000, np.uint16))
    match_frame(np.arange(16.0).reshape(8, 2), np.arange(16.0).reshape(8, 2) + 0.1, 5.0, np.full(8, 2.0))
    view_matrix = np.ones((3, 4))
    view_matrix.flags.writeable = False  # as a geometry's matrices are: the signature the calibration uses
    _predict_from_rays(
        np.ones((1, 8, 3)),
        np.ones((1, 8, 3)),
        np.ones(1, np.int64),
        np.zeros(1, np.int64),
        view_matrix,
        np.zeros((1, 2)),
        np.ones((1, 3, 4)),
    )
    proc = psutil.Process()
    cpu0 = proc.cpu_times()
    load = os.getloadavg()[0]
    if trace:  # tracemalloc slows every allocation: only on request, and then timings are not comparable
        tracemalloc.start()
    # bundle-equal: the bundle with every detection weighted alike (before detections were weighted by background)
    options: dict[str, Any] = {"weigh_detections": False} if method == "bundle-equal" else {}
    if method.endswith("-full"):
        options["bb_search"] = "full"
    res = calib.calibrate_scan(out, method=method.removesuffix("-equal").removesuffix("-full"), **options)
    cpu1 = proc.cpu_times()
    cpu_s = (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system)
    peak_traced = tracemalloc.get_traced_memory()[1] if trace else float("nan")
    tracemalloc.stop()
    rss = psutil.Process().memory_info().rss
    peak_rss = _ru_maxrss()
    with ScanFile(scan) as sf:
        proj = sf.projection_indices
        truth, nominal = sf.geometry("truth")[proj], sf.geometry("nominal")[proj]
        truth_xyz = sf.truth_markers_xyz()
    err_px, _ = similarity_aligned_error_px(res.geometry[proj], truth)
    # reference: bundle from the true projections of the same BBs in the same views, plus the detections' own
    # noise against the truth (per axis)
    ref_err, noise_px = truth_fed_error_px(res.uv[proj], truth, truth_xyz, nominal)
    last = res.iterations[-1]
    queue.put(
        {
            "method": method,
            "frames": res.n_frames,
            "bbs": res.n_bbs,
            "elapsed_s": res.elapsed_s,
            "detect_s": res.detect_s,
            "estimate_s": res.estimate_s,
            "identify_s": res.identify_s,
            "check_s": res.check_s,
            "ms_per_frame": 1000 * res.elapsed_s / res.n_frames,
            "cpu_ms_per_frame": 1000 * cpu_s / res.n_frames,
            "load": load,
            "rpe_mean_mm": last.rpe_mean_mm,
            "rpe_median_mm": last.rpe_median_mm,
            "rpe_std_mm": last.rpe_std_mm,
            "rpe_initial_mm": res.iterations[0].rpe_mean_mm,
            "rpe_iter": [s.rpe_mean_mm for s in res.iterations],
            "reproj_rms_px": res.reproj_rms_px,
            "geom_err_px": err_px,
            "ref_err_px": ref_err,
            "noise_px": noise_px,
            "seen_share": float(np.isfinite(res.uv[proj][..., 0]).mean()),
            "unsolved": len(res.unsolved_views),
            "peak_traced_mb": peak_traced / 2**20,
            "peak_rss_mb": peak_rss / 2**20,
            "rss_mb": rss / 2**20,
        }
    )


def _warm_page_cache(path: Path, block: int = 1 << 24) -> float:
    """Read the file once so the timed run reads frames from memory, as right after an acquisition (on a busy
    disk, reading a cold 0.6-1 GB scan alone takes longer than the whole calibration); returns the seconds taken."""
    t = time.perf_counter()
    with open(path, "rb", buffering=0) as f:
        buf = bytearray(block)
        while f.readinto(buf):
            pass
    return time.perf_counter() - t


def _ru_maxrss() -> float:
    import resource

    return float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024.0


def run_one(scan: Path, method: str, trace: bool = False) -> dict[str, Any]:
    """One calibration in a fresh process."""
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    with tempfile.TemporaryDirectory() as work:
        p = ctx.Process(target=_run, args=(str(scan), method, work, q, trace))
        p.start()
        while True:  # a child that fails ends without an answer: say so instead of waiting for ever
            try:
                out = q.get(timeout=1.0)
                break
            except queue.Empty:
                if not p.is_alive():
                    raise SystemExit(
                        f"the {method} calibration of {scan.name} ended without a result (exit status {p.exitcode})"
                    ) from None
        p.join()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--experiments", default="A,B,C")
    ap.add_argument(
        "--methods",
        default="bundle,paper",
        help="bundle, paper, bundle-equal (the bundle weighting every detection alike), bundle-full (every frame "
        "searched whole for BBs: bb_search full, not round those found before)",
    )
    ap.add_argument("--size", type=int, default=768, help="detector size (px)")
    ap.add_argument("--frames-scale", type=float, default=1.0, help="fraction of the paper's frame counts")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tracemalloc", action="store_true", help="also report the peak of traced Python allocations")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "orbitct-calib-bench")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    from calib.report import PAPER_TABLE1

    print(f"machine: {cpu_model()}, {os.cpu_count()} cores, {platform.python_version()}")
    rows: list[tuple[str, dict[str, Any]]] = []
    for exp in args.experiments.split(","):
        frames = max(20, int(round(PAPER_FRAMES[exp] * args.frames_scale)))
        scan = cached_scan(args.cache, exp, args.size, frames, args.seed)
        for method in args.methods.split(","):
            r = run_one(scan, method, args.tracemalloc)
            rows.append((exp, r))
            print(
                f"  {exp} {method:6s}: {r['bbs']} BBs, {r['elapsed_s']:.2f} s ({r['ms_per_frame']:.2f} ms/frame), "
                f"RPE {r['rpe_mean_mm']:.4f} mm, geometry error {r['geom_err_px']:.3f} px (ref {r['ref_err_px']:.3f})",
                flush=True,
            )
    print()
    print(f"# Calibration benchmark ({args.size} x {args.size} px; frames = {args.frames_scale:g} x the paper's)\n")
    head = (
        "| exp | method | frames | BBs | total s | ms/frame | ms/frame/BB | detect s | identify s | estimate s | check s | "
        "RPE mean / median / std (mm) | initial RPE | reproj px | geom err px | ref err px | ratio | noise px | "
        "seen | peak traced MB | peak RSS MB | CPU ms/frame | load |"
    )
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for exp, r in rows:
        ratio = r["geom_err_px"] / r["ref_err_px"] if r["ref_err_px"] > 0 else float("nan")
        print(
            f"| {exp} | {r['method']} | {r['frames']} | {r['bbs']} | {r['elapsed_s']:.2f} | {r['ms_per_frame']:.2f} | "
            f"{r['ms_per_frame'] / max(r['bbs'], 1):.3f} | {r['detect_s']:.2f} | {r['identify_s']:.2f} | {r['estimate_s']:.2f} | "
            f"{r['check_s']:.2f} | "
            f"{r['rpe_mean_mm']:.4f} / {r['rpe_median_mm']:.4f} / {r['rpe_std_mm']:.4f} | {r['rpe_initial_mm']:.3f} | "
            f"{r['reproj_rms_px']:.3f} | {r['geom_err_px']:.3f} | {r['ref_err_px']:.3f} | {ratio:.2f} | {r['noise_px']:.3f} | "
            f"{r['seen_share']:.2f} | {r['peak_traced_mb']:.0f} | {r['peak_rss_mb']:.0f} | {r['cpu_ms_per_frame']:.2f} | {r['load']:.1f} |"
        )
    print("\nRPE mean per iteration (0 = nominal geometry):")
    for exp, r in rows:
        print(
            f"  {exp} {r['method']:6s}: "
            + ", ".join(f"{v:.4f}" for v in r["rpe_iter"][:8])
            + (" ..." if len(r["rpe_iter"]) > 8 else "")
        )
    print("\nPaper (Ma et al. 2022, Table 1, after 2 iterations, MATLAB on a laptop):")
    print("| exp | frames | BBs | elapsed s | RPE mean / median / std (mm) | s/frame | s/frame/BB |")
    print("|---|---|---|---|---|---|---|")
    for exp in args.experiments.split(","):
        p = PAPER_TABLE1[exp]
        print(
            f"| {exp} | {p['frames']:.0f} | {p['bbs']:.0f} | {p['elapsed_s']:.0f} | {p['rpe_mean_mm']} / {p['rpe_median_mm']} / "
            f"{p['rpe_std_mm']} | {p['s_per_frame']} | {p['s_per_frame_per_bb']} |"
        )
    print("\nCPU ms/frame: user+system CPU time of the calibration process per frame (all threads); on a machine")
    print("shared with other work (load = 1-min load average at the start) wall time overstates the cost.")
    print("\nTargets for bundle: < 6 ms/frame, geometry error <= 2x reference, peak RSS < 1024 MB (857 frames).")


if __name__ == "__main__":
    main()
