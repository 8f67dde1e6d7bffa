"""One reconstruction split across the workers of a Dask cluster (``dask.distributed``).

FDK is a sum over views: the views are cut into parts (two per worker), each worker reads its part's frames from
the scan file itself (the workers see the file at the same path: a shared disk), filters and back-projects them
with the whole orbit's weights (:class:`recon.fdk.FdkWeights`), and the partial volumes are summed pairwise on the
workers as they finish (the transfers of a level run side by side); only the sum comes back. The result equals one process's within float32 round-off (the order of
the sum differs). A part is read-only work, so when a worker is lost Dask runs it again elsewhere.
"""

from __future__ import annotations

import os
import time
import uuid
from typing import Any

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry, VolumeGrid
from orbitct.progress import ProgressCallback, report
from orbitct.scanfile import ScanFile
from recon.errors import ReconError
from recon.fdk import FdkWeights, fdk_views
from recon.stack import FileLineIntegrals

#: parts per worker: a part that finishes late on a slow worker then holds up less
PARTS_PER_WORKER = 2


class ClusterError(ReconError):
    """The cluster cannot be reached, has no workers, or lost the work."""


def _fdk_part(path: str, frames: NDArray[np.intp], grid: VolumeGrid, geometry: ViewGeometry,
              weights: FdkWeights) -> NDArray[np.float32]:
    """On a worker: the back-projection of some views, read from the scan file."""
    with ScanFile(path) as scan:
        return fdk_views(FileLineIntegrals(scan, frames), grid, geometry, weights)


def _sum(a: NDArray[np.float32], b: NDArray[np.float32]) -> NDArray[np.float32]:
    return np.add(a, b)  # a new array: a task run again after a lost worker must find its inputs unchanged


def fdk_on_cluster(client: Any, path: str | os.PathLike[str], frames: NDArray[np.intp], grid: VolumeGrid,
                   geometry: ViewGeometry, *, window: str = "ram-lak", progress: ProgressCallback | None = None,
                   workers_timeout_s: float = 30.0) -> NDArray[np.float32]:
    """FDK of the projections ``frames`` of the scan at ``path`` (their ``geometry``) on the workers of ``client``."""
    try:
        client.wait_for_workers(1, timeout=workers_timeout_s)
    except Exception as exc:  # noqa: BLE001 - any failure to find a worker is the same answer
        raise ClusterError(f"no Dask worker joined the scheduler {client.scheduler.address} within "
                           f"{workers_timeout_s:g} s ({type(exc).__name__})") from None
    n_workers = max(1, len(client.scheduler_info()["workers"]))
    weights = FdkWeights.of(geometry, window)
    n_parts = int(min(frames.size, PARTS_PER_WORKER * n_workers))
    bounds = np.linspace(0, frames.size, n_parts + 1).astype(int)
    run = uuid.uuid4().hex[:8]
    parts = [client.submit(_fdk_part, os.fspath(path), frames[a:b], grid, geometry[a:b], weights.part(slice(a, b)),
                           key=f"orbitct-fdk-{run}-{i}", pure=False)
             for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True))]
    sizes = dict(zip((p.key for p in parts), np.diff(bounds).tolist(), strict=True))
    pending, ready, done, sums = list(parts), [], 0, 0
    while pending or len(ready) > 1:  # sum finished parts pairwise on the workers: the transfers run side by side
        finished = [f for f in pending if f.status != "pending"]
        if not finished:
            time.sleep(0.02)
            continue
        for f in finished:
            if f.status != "finished":  # an error, or a scheduler that went away: say so rather than wait
                why = f"{type(f.exception()).__name__}: {f.exception()}" if f.status == "error" else f.status
                raise ClusterError(f"the cluster lost the FDK of {os.fspath(path)} ({why}); the scheduler "
                                   f"{client.scheduler.address} went away or a part failed")
            pending.remove(f)
            ready.append(f)
            if f.key in sizes:
                done += sizes[f.key]
                report(progress, "fdk", done, int(frames.size), f"views ({n_workers} workers)")
        while len(ready) >= 2:
            a, b = ready.pop(0), ready.pop(0)
            sums += 1
            pending.append(client.submit(_sum, a, b, key=f"orbitct-fdk-{run}-sum{sums}", pure=False))
    total = ready[0]
    try:
        return np.asarray(total.result(), dtype=np.float32)
    except Exception as exc:  # noqa: BLE001 - reported with what was lost
        raise ClusterError(f"the cluster lost the FDK of {os.fspath(path)}: {type(exc).__name__}: {exc}") from None


__all__ = ["ClusterError", "PARTS_PER_WORKER", "fdk_on_cluster"]
