"""What every benchmark prints about the machine it ran on."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (or what platform knows)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def cores_available() -> int:
    """Cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def describe_machine() -> str:
    """One line: CPU, usable cores, 1-minute load average, OS and Python."""
    load = f", load {os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else ""
    return (
        f"{cpu_model()}, {cores_available()} cores available{load}, "
        f"{platform.system()} {platform.release()}, Python {platform.python_version()}"
    )


def machine_peaks() -> tuple[float, float]:
    """This machine's float32 arithmetic rate and copy bandwidth, each the best of three runs on all cores.

    Arithmetic: GFLOP/s of a 2048 x 2048 float32 matrix product (numpy's BLAS, about as close to the cores' peak as
    tuned code gets). Copy: GB/s read plus written by a parallel copy of 512 MiB (far larger than the caches).
    """
    import time

    import numba
    import numpy as np

    @numba.njit(parallel=True, cache=False)
    def copy(src, dst):  # type: ignore[no-untyped-def]
        for i in numba.prange(src.shape[0]):
            dst[i] = src[i]

    a = np.random.default_rng(0).random((2048, 2048), dtype=np.float32)
    src = np.ones(2**27, np.float32)
    dst = np.empty_like(src)
    copy(src[:16], dst[:16])
    flop_s, copy_s = [], []
    for _ in range(3):
        t = time.perf_counter()
        a @ a
        flop_s.append(time.perf_counter() - t)
        t = time.perf_counter()
        copy(src, dst)
        copy_s.append(time.perf_counter() - t)
    return 2 * 2048**3 / min(flop_s) / 1e9, 2 * src.nbytes / min(copy_s) / 1e9
