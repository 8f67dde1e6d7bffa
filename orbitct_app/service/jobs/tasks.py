"""What a job worker process runs: calibration and reconstruction of a scan file, with their result files."""

from __future__ import annotations

import contextlib
import csv
import math
import socket
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from orbitct.progress import ProgressEvent
from orbitct.verdict import Verdict


def _finite(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _quality(verdict: Any) -> dict[str, Any] | None:
    if verdict is None:
        return None
    out = verdict.summary()
    for key in ("predicted_px_median", "predicted_px_max", "centroid_noise_px"):
        out[key] = _finite(out[key])
    return out


def run_calibration(
    scan_path: Path, params: dict[str, Any], out_dir: Path, progress: Callable[[ProgressEvent], None]
) -> dict[str, Any]:
    """Calibrate the scan in place; report plots and the RPE table go to ``out_dir``."""
    import calib

    options = {k: v for k, v in params.items() if k != "method" and v is not None}
    res = calib.calibrate_scan(
        scan_path, method=params.get("method", "bundle"), out=None, report_dir=out_dir, progress=progress, **options
    )
    rpe = np.asarray(res.rpe_mm, dtype=float)
    with open(out_dir / "rpe_per_frame.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "rpe_mm"])
        for i, value in enumerate(rpe):
            if math.isfinite(value):
                w.writerow([i, f"{value:.6f}"])
    iterations = [
        {
            "index": it.index,
            "rpe_mean_mm": _finite(it.rpe_mean_mm),
            "rpe_median_mm": _finite(it.rpe_median_mm),
            "rpe_std_mm": _finite(it.rpe_std_mm),
            "reproj_rms_px": _finite(it.reproj_rms_px),
        }
        for it in res.iterations
    ]
    final = res.iterations[-1]
    table = {
        "frames": int(res.n_frames),
        "bbs": int(res.n_bbs),
        "elapsed_s": float(res.elapsed_s),
        "rpe_mean_mm": _finite(final.rpe_mean_mm),
        "rpe_median_mm": _finite(final.rpe_median_mm),
        "rpe_std_mm": _finite(final.rpe_std_mm),
        "time_per_frame_s": float(res.elapsed_s) / max(int(res.n_frames), 1),
        "time_per_frame_per_bb_s": float(res.elapsed_s) / max(int(res.n_frames) * int(res.n_bbs), 1),
    }
    return {
        "method": res.method,
        "table": table,
        "iterations": iterations,
        "reproj_rms_px": _finite(res.reproj_rms_px),
        "warnings": [str(w) for w in res.warnings][:200],
        "unsolved_views": [int(v) for v in res.unsolved_views][:10_000],
        "quality": _quality(res.quality),
        "verdict": (
            Verdict.summary(res.quality)
            if res.quality is not None
            else Verdict(reasons=("the calibration made no quality check",)).summary()
        ),
        "scale": res.scale_line(),
        "files": sorted(p.name for p in out_dir.iterdir() if p.is_file()),
    }


def run_reconstruction(
    scan_path: Path, params: dict[str, Any], out_dir: Path, progress: Callable[[ProgressEvent], None]
) -> dict[str, Any]:
    """Reconstruct the scan into ``/recon/<name>``; slices, NIfTI and a raw copy of the volume go to ``out_dir``."""
    import recon
    from recon.device import resolve_device

    options = recon.ReconstructionOptions.model_validate(params)  # the request's options, as it was accepted
    device = resolve_device(options.device)
    # the views of FDK and PWLS across the workers, unless this worker has a usable GPU (or MAR, which runs here)
    split = not options.mar and device == "cpu"
    with (
        one_job_per_gpu(progress) if device == "cuda" else contextlib.nullcontext(),
        _cluster_client() if split else contextlib.nullcontext() as cluster,
    ):
        res = recon.reconstruct_scan(
            scan_path, options, export=["nifti", "png"], out_dir=out_dir, progress=progress, cluster=cluster
        )
    volume = np.asarray(res.volume, dtype=np.float32)
    np.save(out_dir / "volume.npy", volume)
    return {
        "name": res.name,
        "shape": [int(n) for n in res.volume_shape],
        "voxel_mm": [float(v) for v in res.voxel_mm],
        "origin_mm": [float(v) for v in res.origin_mm],
        "cost": [_finite(c) for c in res.cost],
        "elapsed_s": float(res.elapsed_s),
        "estimated_s": _finite(res.params.get("estimated_s", float("nan"))),
        "min": _finite(volume.min()),
        "max": _finite(volume.max()),
        "mean": _finite(volume.mean()),
        "warnings": [str(w) for w in res.warnings],
        "verdict": res.verdict.summary(),
        "geometry_override": bool(res.params.get("geometry_override", False)),
        "workers": int(res.params.get("cluster_workers", 1)),
        "device": str(res.params["device"]),
        "device_peak_bytes": int(res.params.get("device_peak_bytes", 0)),
        "files": sorted(p.name for p in out_dir.iterdir() if p.is_file()),
    }


@contextlib.contextmanager
def one_job_per_gpu(progress: Callable[[ProgressEvent], None] | None = None) -> Iterator[None]:
    """On a Dask worker: hold this machine's GPU for the block (a cluster-wide lock named after the host), so two
    reconstruction jobs never share one GPU; a job that has to wait says so. Elsewhere: nothing to hold."""
    try:
        from distributed import Lock, get_worker

        get_worker()
    except (ImportError, ValueError):
        yield
        return
    lock = Lock(f"orbitct-gpu-{socket.gethostname()}")
    if not lock.acquire(timeout=0):
        if progress is not None:
            progress(ProgressEvent("gpu", 0, 1, "waiting for the GPU: another reconstruction is using it"))
        lock.acquire()
    try:
        yield
    finally:
        lock.release()


@contextlib.contextmanager
def _cluster_client() -> Iterator[Any]:
    """On a worker of a Dask cluster with two or more workers: a client of that cluster (the job's thread leaves the
    worker's pool meanwhile, so the parts can run there too); otherwise None."""
    try:
        from distributed import get_worker, worker_client

        get_worker()
    except (ImportError, ValueError):
        yield None
        return
    with worker_client() as client:
        yield client if len(client.scheduler_info()["workers"]) >= 2 else None
