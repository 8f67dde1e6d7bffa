"""Benchmark: reconstruction on one GPU (``--device cuda``) at the full size of experiment A, beside diffct.

Run on a machine with an NVIDIA GPU and the gpu extra (``pip install -e '.[gpu]'``; diffct for the comparison:
``pip install diffct==2.5.0 torch``). Prints the machine and its GPU, then one table: forward and matched back
projection (kernel time, data already on the GPU, and from host memory to host memory), FDK, one PWLS iteration,
50 plain SPS iterations, the accelerated PWLS (12 ordered subsets with momentum) to within 1 % of the RMSE of those
50, and ``orbitct reconstruct --device cuda`` from the scan file to the written volume, each with the GPU memory
orbitct's arrays held; diffct's forward and back projection of the same volume along the same rays in the same run,
and the ratios.

    python benchmarks/gpu.py                          # 500 views of 768 x 768, 0.5 mm voxels on the fitted grid
    python benchmarks/gpu.py --size 256 --frames 200 --voxel-mm 1.5 --no-diffct

Targets on one H200 (issue 41): forward and back each at least as fast as diffct; FDK under 0.35 s; 50 plain SPS
under 15 s; accelerated PWLS under 3 s; the command end to end under 10 s.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

import numpy as np
from full_size_recon import METAL_MU, WITHIN, _scan
from machine_info import describe_machine


def _best(fn: Callable[[], Any], repeat: int = 3) -> float:
    """Best wall time of ``repeat`` runs after one warm-up (compiling), the GPU synchronised around each."""
    from numba import cuda

    fn()
    cuda.synchronize()
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        cuda.synchronize()
        best = min(best, time.perf_counter() - t)
    return best


def _diffct_times(geometry: Any, grid: Any, x: np.ndarray, ours: np.ndarray) -> tuple[float, float, float] | None:
    """diffct's forward and back projection times of the same volume along the same rays, and how far its
    projections are from ours (relative RMS); None when diffct or torch is not installed."""
    try:
        import torch
        from diffct import ConeBackprojectorFunction, ConeProjectorFunction
    except ImportError as exc:
        print(f"diffct not measured: {exc}")
        return None
    centre = np.asarray(grid.origin_mm) + (np.asarray(grid.shape[::-1]) - 1) / 2 * np.asarray(grid.voxel_mm)
    det = geometry.panel
    c0, r0 = det.center
    d_centre = geometry.D + ((det.cols - 1) / 2 - c0) * geometry.u + ((det.rows - 1) / 2 - r0) * geometry.v
    t = {
        k: torch.tensor(v, dtype=torch.float32, device="cuda")
        for k, v in {
            "src": geometry.S - centre,
            "det": d_centre - centre,
            "u": geometry.u / np.linalg.norm(geometry.u, axis=1, keepdims=True),
            "v": geometry.v / np.linalg.norm(geometry.v, axis=1, keepdims=True),
        }.items()
    }
    vol = torch.tensor(x, device="cuda")
    voxel = float(grid.voxel_mm[0])

    def fwd() -> Any:
        return ConeProjectorFunction.apply(
            vol, t["src"], t["det"], t["u"], t["v"], det.cols, det.rows, det.pitch_col, det.pitch_row, voxel
        )

    sino = fwd()
    nz, ny, nx = grid.shape

    def back() -> Any:
        return ConeBackprojectorFunction.apply(
            sino, t["src"], t["det"], t["u"], t["v"], nz, ny, nx, det.pitch_col, det.pitch_row, voxel
        )

    theirs = sino.permute(0, 2, 1).cpu().numpy()  # (views, cols, rows) -> ours (views, rows, cols)
    off = float(np.sqrt(np.mean((theirs - ours) ** 2)) / max(np.sqrt(np.mean(ours**2)), 1e-30))
    return _best(fwd), _best(back), off


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=768, help="detector pixels per side")
    ap.add_argument("--frames", type=int, default=500, help="projections")
    ap.add_argument("--voxel-mm", type=float, default=0.5)
    ap.add_argument("--sps-iterations", type=int, default=50, help="plain SPS iterations of the reference")
    ap.add_argument("--passes", type=int, default=8, help="most passes of the accelerated PWLS")
    ap.add_argument("--no-diffct", action="store_true", help="leave diffct out")
    ap.add_argument("--cache", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "orbitct-gpu-bench")
    args = ap.parse_args()
    from recon.device import describe_device, gpu_problem

    problem = gpu_problem()
    if problem is not None:
        raise SystemExit(f"no GPU to measure: {problem}")
    import recon
    from orbitct.scanfile import ScanFile
    from recon.cuda import CudaProjector, peak_bytes, reset_peak
    from recon.operator import pad_volume
    from recon.quality import reference_volume
    from recon.stack import FileLineIntegrals, FileWeights

    args.cache.mkdir(parents=True, exist_ok=True)
    print(describe_machine())
    print(f"device: {describe_device('cuda')}")
    print(
        f"experiment A, {args.size} px, {args.frames} frames, {args.voxel_mm:g} mm voxels (fitted grid)\n", flush=True
    )
    scan = _scan(args.cache, args.size, args.frames)
    rows: list[tuple[str, float, float | None, str]] = []
    with tempfile.TemporaryDirectory(dir=args.cache) as work:
        copy = Path(work) / "scan.h5"
        shutil.copyfile(scan, copy)
        cli = [str(Path(sys.executable).with_name("orbitct")), "reconstruct", str(copy), "--geometry", "truth"]
        cli += ["--voxel-mm", str(args.voxel_mm), "--device", "cuda", "--overwrite", "--yes"]
        for sitting in ("first run", "second run (CPU kernels cached; CUDA kernels compile in every process)"):
            t = time.perf_counter()
            subprocess.run(cli, check=True, capture_output=True)
            rows.append((f"orbitct reconstruct --device cuda, {sitting}", time.perf_counter() - t, None, ""))
        fdk_res = recon.reconstruct_scan(copy, geometry="truth", voxel_mm=args.voxel_mm, device="cuda", name="g")
        grid = fdk_res.grid
        with ScanFile(copy) as sf:
            truth = reference_volume(sf.phantom, grid)
            frames = sf.projection_indices
            geometry = sf.geometry("truth")[frames]
            y = FileLineIntegrals(sf, frames)[np.arange(frames.size)]
            w = FileWeights(sf, frames)[np.arange(frames.size)]
    mask = truth < METAL_MU
    print(f"grid {grid.shape} voxels of {args.voxel_mm:g} mm\n", flush=True)
    from numba import cuda

    A = CudaProjector(grid, geometry)
    x = np.maximum(fdk_res.volume, 0).astype(np.float32)
    xp = pad_volume(x)
    d_xp = cuda.to_device(xp.reshape(-1))
    per_view = geometry.panel.rows * geometry.panel.cols
    chunks = A.chunks(0, geometry.n_views)
    d_out = [cuda.device_array((j1 - j0) * per_view, np.float32) for j0, j1 in chunks]
    d_acc = cuda.device_array(xp.size, np.float32)

    def forward() -> None:
        for (j0, j1), d in zip(chunks, d_out):
            A.forward_on_device(d_xp, d, j0, j1)

    def back() -> None:
        for (j0, j1), d in zip(chunks, d_out):
            A.back_on_device(d, d_acc, j0, j1)

    ours = A(x)
    reset_peak()
    rows.append(("forward projection (on the GPU)", _best(forward), None, ""))
    rows.append(("back projection (on the GPU)", _best(back), None, ""))
    rows.append(("forward projection (host to host)", _best(lambda: A(x)), peak_bytes(), ""))
    rows.append(("back projection (host to host)", _best(lambda: A.T(ours)), peak_bytes(), ""))
    reset_peak()
    rows.append(
        (
            "FDK (hann)",
            _best(lambda: recon.fdk(y, grid, geometry, device="cuda")),
            peak_bytes(),
            "",
        )
    )

    def pwls(iterations: int, subsets: int, momentum: bool, rmses: list[float]) -> float:
        reset_peak()
        t = time.perf_counter()
        recon.pwls_sps(A, y, w, iterations=iterations, subsets=subsets, momentum=momentum, x0=x,
                       callback=lambda _, im: rmses.append(recon.rmse(im, truth, mask)))  # fmt: skip
        return time.perf_counter() - t

    one: list[float] = []
    rows.append(("PWLS, one iteration", pwls(1, 1, False, one), peak_bytes(), ""))
    ref: list[float] = []
    t_ref = pwls(args.sps_iterations, 1, False, ref)
    rows.append((f"plain SPS, {args.sps_iterations} iterations", t_ref, peak_bytes(), f"RMSE {ref[-1]:.5f}"))
    acc: list[float] = []
    t_acc = pwls(args.passes, 12, True, acc)
    reached = next((k + 1 for k, r in enumerate(acc) if r <= WITHIN * ref[-1]), None)
    note = f"{reached} passes reach it" if reached else f"not within 1 % in {args.passes} passes"
    rows.append(
        ("accelerated PWLS (12 subsets, momentum)", t_acc * (reached or args.passes) / args.passes, peak_bytes(), note)
    )
    theirs = None if args.no_diffct else _diffct_times(geometry, grid, x, ours)
    print("| step | orbitct s | GPU memory GiB | diffct s | diffct / orbitct | note |\n|---|---|---|---|---|---|")
    for name, s, mem, note in rows:
        d = None
        if theirs is not None and name.startswith(("forward projection (on", "back projection (on")):
            d = theirs[0] if name.startswith("forward") else theirs[1]
            note = f"diffct's projections differ by {theirs[2]:.1%} RMS (Siddon, cell-constant voxels)"
        memory = f"{mem / 2**30:.2f}" if mem else "-"
        ratio = f"{d / s:.2f}x" if d else "-"
        print(f"| {name} | {s:.3f} | {memory} | {f'{d:.3f}' if d else '-'} | {ratio} | {note} |")


if __name__ == "__main__":
    main()
