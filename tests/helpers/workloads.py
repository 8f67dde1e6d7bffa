"""Small real job workloads for the job framework tests (run in worker processes like the real jobs)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from orbitct.progress import ProgressEvent, report
from orbitct.scanfile import ScanFile


def frame_means(
    scan_path: Path, params: dict[str, Any], out_dir: Path, progress: Callable[[ProgressEvent], None]
) -> dict[str, Any]:
    """Mean of every frame of the scan, one progress event per frame, optionally slowed down."""
    delay = float(params.get("delay_s", 0.0))
    with ScanFile(scan_path) as sf:
        means = []
        for i in range(sf.n_frames):
            means.append(float(np.mean(sf.frames[i])))
            report(progress, "means", i + 1, sf.n_frames, f"frame {i}", mean=means[-1])
            time.sleep(delay)
    np.save(out_dir / "means.npy", np.asarray(means))
    if params.get("fail"):
        raise ValueError("asked to fail after the means")
    return {"n": len(means), "first": means[0] if means else None}
