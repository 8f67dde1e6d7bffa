"""One reconstruction split across the workers of a Dask cluster (``dask.distributed``).

The workers see the scan file at the same path (a shared disk) and read their own views from it; only volumes
travel. **FDK** is a sum over views: the views are cut into parts (two per worker), each filtered and
back-projected with the whole orbit's weights (:class:`recon.fdk.FdkWeights`). **PWLS** keeps one part of the
views per worker for the whole run (its line integrals and weights loaded once, in the worker's memory); for
each ordered subset the iterate is broadcast to the workers, each returns its views' share of the subset's
gradient and data term, and the solver's step (penalty, surrogate, momentum) runs here. In both, partial volumes
are summed pairwise on the workers as they finish (the transfers of a level run side by side); only the sum comes
back. The result equals one process's within float32 round-off (the order of the sum differs). Every task is
read-only work, so when a worker is lost Dask runs it again elsewhere (a part of the views is read again).
"""

from __future__ import annotations

import itertools
import logging
import os
import threading
import time
import uuid
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry, VolumeGrid
from orbitct.progress import ProgressCallback, report
from orbitct.scanfile import ScanFile
from recon.device import resolve_device
from recon.errors import ReconError
from recon.fdk import FdkWeights, fdk_views
from recon.operator import projector
from recon.options import DEFAULT_BETA
from recon.pwls import ViewsData, pwls_solve
from recon.pwls_setup import PwlsResult
from recon.stack import FileLineIntegrals, FileWeights

if TYPE_CHECKING:
    from recon.cuda import CudaViewsData

log = logging.getLogger(__name__)
LOSS_CHECK_S = 1.0  # how often a PWLS on a cluster looks whether the workers holding its views are still there
#: FDK's parts per worker: a part that finishes late on a slow worker then holds up less
PARTS_PER_WORKER = 2
STEP_TRIES = 3  # how often a PWLS step whose work died with a worker is run again on the workers left


class ClusterError(ReconError):
    """The cluster cannot be reached, has no workers, or lost the work."""


class WorkLostError(ClusterError):
    """Work came back cancelled or lost: a worker died holding it, or holding data it needed."""


def _fdk_part(
    path: str, frames: NDArray[np.intp], grid: VolumeGrid, geometry: ViewGeometry, weights: FdkWeights, device: str
) -> NDArray[np.float32]:
    """On a worker: the back-projection of some views, read from the scan file, on ``device`` as that worker
    resolves it (``auto``: its GPU when it has a usable one)."""
    with ScanFile(path) as scan:
        return fdk_views(FileLineIntegrals(scan, frames), grid, geometry, weights, device=resolve_device(device))


def _sum(a: Any, b: Any) -> Any:
    """Two partial results added (arrays, or tuples of arrays and numbers, element by element); a new object: a
    task run again after a lost worker must find its inputs unchanged."""
    if isinstance(a, tuple):
        return tuple(np.add(u, v) for u, v in zip(a, b, strict=True))
    return np.add(a, b)


def _connected_workers(client: Any, timeout_s: float) -> list[str]:
    """The addresses of the cluster's workers, waiting up to ``timeout_s`` for the first one."""
    try:
        client.wait_for_workers(1, timeout=timeout_s)
        return sorted(client.scheduler_info()["workers"])
    except Exception as exc:  # noqa: BLE001 - any failure to find a worker is the same answer
        raise ClusterError(
            f"no Dask worker joined the scheduler {client.scheduler.address} within "
            f"{timeout_s:g} s ({exc or 'no answer'}); start a worker (dask worker {client.scheduler.address})"
        ) from None


def _sum_on_workers(
    client: Any, parts: list[Any], what: str, key: str, done: Callable[[Any], None] | None = None
) -> Any:
    """The sum of the results of ``parts``, added pairwise on the workers as they finish; only the sum is fetched.
    ``done(future)`` is called as each part finishes. A part that fails, or a scheduler that goes away, raises
    :class:`ClusterError` naming ``what`` rather than waiting."""
    pending, sums = list(parts), 0
    ready: list[Any] = []
    first = {f.key for f in parts}
    while pending or len(ready) > 1:
        finished = [f for f in pending if f.status != "pending"]
        if not finished:
            time.sleep(0.005)
            continue
        for f in finished:
            if f.status == "error":
                raise ClusterError(f"a part of {what} failed on its Dask worker: {_sentence(f.exception())}")
            if f.status != "finished":
                raise WorkLostError(
                    f"the cluster lost {what} ({f.status}): a worker died holding it, or the scheduler "
                    f"{client.scheduler.address} went away"
                )
            pending.remove(f)
            ready.append(f)
            if done is not None and f.key in first:
                done(f)
        while len(ready) >= 2:
            a, b = ready.pop(0), ready.pop(0)
            sums += 1
            pending.append(client.submit(_sum, a, b, key=f"{key}-sum{sums}", pure=False))
    try:
        return ready[0].result()
    except Exception as exc:  # noqa: BLE001 - reported with what was lost
        raise ClusterError(f"the cluster lost {what}: {_sentence(exc)}") from None


def _sentence(exc: BaseException | None) -> str:
    """What ``exc`` says, for a person: its message, or what kind of failure it was when it has none."""
    text = str(exc or "").strip()
    return text or "the worker gave no reason (see its log)"


def fdk_on_cluster(
    client: Any,
    path: str | os.PathLike[str],
    frames: NDArray[np.intp],
    grid: VolumeGrid,
    geometry: ViewGeometry,
    *,
    window: str = "ram-lak",
    progress: ProgressCallback | None = None,
    workers_timeout_s: float = 30.0,
    device: str = "auto",
) -> NDArray[np.float32]:
    """FDK of the projections ``frames`` of the scan at ``path`` (their ``geometry``) on the workers of ``client``
    (each on ``device`` as it resolves it: ``auto`` takes its GPU when it has a usable one)."""
    n_workers = len(_connected_workers(client, workers_timeout_s))
    weights = FdkWeights.of(geometry, window)
    n_parts = int(min(frames.size, PARTS_PER_WORKER * n_workers))
    bounds = np.linspace(0, frames.size, n_parts + 1).astype(int)
    key = f"orbitct-fdk-{uuid.uuid4().hex[:8]}"
    parts = [
        client.submit(
            _fdk_part,
            os.fspath(path),
            frames[a:b],
            grid,
            geometry[a:b],
            weights.part(slice(a, b)),
            device,
            key=f"{key}-{i}",
            pure=False,
        )
        for i, (a, b) in enumerate(itertools.pairwise(bounds))
    ]
    sizes = dict(zip((p.key for p in parts), np.diff(bounds).tolist(), strict=True))
    count = [0]

    def done(f: Any) -> None:
        count[0] += sizes[f.key]
        report(progress, "fdk", count[0], int(frames.size), f"views ({n_workers} workers)")

    total = _sum_on_workers(client, parts, f"the FDK of {os.fspath(path)}", key, done)
    return np.asarray(total, dtype=np.float32)


class ViewPart:
    """On a worker: a run of a scan's views held for a PWLS run (line integrals and weights read once) and their
    share of its data term. Its subsets are the run's: global view ``offset + j`` is in subset ``(offset + j) % M``.

    Pickled as the recipe, not the data: moved or spilled, it reads its views from the file again.
    """

    def __init__(
        self,
        path: str,
        frames: NDArray[np.intp],
        offset: int,
        grid: VolumeGrid,
        geometry: ViewGeometry,
        subsets: int,
        chunk_views: int = 8,
        device: str = "auto",
    ) -> None:
        self._recipe = (path, frames, offset, grid, geometry, subsets, chunk_views, device)
        with ScanFile(path) as scan:
            every = np.arange(frames.size)
            y, w = FileLineIntegrals(scan, frames)[every], FileWeights(scan, frames)[every]
        index = offset + np.arange(frames.size)
        subset_views = [np.flatnonzero(index % subsets == m) for m in range(subsets)]
        self.data: ViewsData | CudaViewsData
        if resolve_device(device) == "cuda":  # this worker's GPU
            from recon.cuda import CudaProjector, CudaViewsData

            self.data = CudaViewsData(CudaProjector(grid, geometry), y, w, subset_views=subset_views)
        else:
            self.data = ViewsData(projector(grid, geometry), y, w, chunk_views=chunk_views, subset_views=subset_views)
        self._lock = threading.Lock()  # one projector: one task at a time on it
        self._nbytes = y.nbytes + w.nbytes

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return (ViewPart, self._recipe)

    def __sizeof__(self) -> int:  # what Dask counts for it: the views it holds
        return self._nbytes

    def curvature(self) -> NDArray[np.float32]:
        """This part's ``A^T (w * A 1)`` (padded)."""
        out = np.zeros(self.data.padded_shape, np.float32)
        with self._lock:
            self.data.curvature(out)
        return out

    def gradient(self, xp: NDArray[np.float32], subset: int, with_gradient: bool) -> tuple[Any, ...]:
        """(gradient, term) of this part's views in ``subset`` at ``xp``; (term,) without the gradient."""
        out = np.zeros(self.data.padded_shape, np.float32) if with_gradient else None
        with self._lock:
            value = self.data.gradient(xp, subset, out)
        return (value,) if out is None else (out, value)


def _part_curvature(part: ViewPart) -> NDArray[np.float32]:
    return part.curvature()


def _part_gradient(part: ViewPart, xp: NDArray[np.float32], subset: int, with_gradient: bool) -> tuple[Any, ...]:
    return part.gradient(xp, subset, with_gradient)


def check_pwls_memory(client: Any, n_views: int, geometry: ViewGeometry, grid: VolumeGrid) -> None:
    """Refuse, before anything runs, PWLS whose part of the views would not fit in a worker's memory limit (one
    part per worker: its line integrals and weights, and the two volumes a task holds, the iterate it was sent
    and its gradient). :class:`ClusterError` says what is needed and what to do."""
    info = client.scheduler_info()["workers"]
    workers = sorted(info)[: min(n_views, len(info))]  # one part each (none yet: found out when waiting for them)
    views = -(-n_views // max(1, len(workers)))
    panel = geometry.panel
    padded = int(np.prod([n + 2 for n in grid.shape]))
    needed = 2 * 4 * views * panel.rows * panel.cols + 2 * 4 * padded
    limits = [int(info[w].get("memory_limit") or 0) for w in workers]
    tight = [lim for lim in limits if 0 < lim < needed / 0.8]  # Dask pauses a worker at 80 % of its limit
    if tight:
        raise ClusterError(
            f"PWLS on the cluster needs about {needed / 2**30:.2f} GiB on each of {len(workers)} "
            f"worker(s) ({views} views of {panel.rows} x {panel.cols} pixels and two volumes), more "
            f"than 80 % of a worker's memory limit ({min(tight) / 2**30:.2f} GiB); add workers, give them "
            "more memory (dask worker --memory-limit), or use a larger voxel size"
        )


class ClusterData:
    """The PWLS data term (:class:`recon.pwls.DataTerm`) of a scan's views spread over a cluster's workers, one
    :class:`ViewPart` each. Close it (or use it as a context manager) to free the workers' memory."""

    def __init__(
        self,
        client: Any,
        path: str | os.PathLike[str],
        frames: NDArray[np.intp],
        grid: VolumeGrid,
        geometry: ViewGeometry,
        *,
        subsets: int = 1,
        chunk_views: int = 8,
        workers_timeout_s: float = 30.0,
        device: str = "auto",
    ) -> None:
        if subsets < 1:
            raise ReconError(f"need subsets >= 1, got {subsets}")
        workers = _connected_workers(client, workers_timeout_s)
        self.client, self.subsets = client, subsets
        nz, ny, nx = grid.shape
        self.padded_shape = (nz + 2, ny + 2, nx + 2)
        self.what = f"the PWLS of {os.fspath(path)}"
        self._key = f"orbitct-pwls-{uuid.uuid4().hex[:8]}"
        self._calls = 0
        bounds = np.linspace(0, frames.size, int(min(frames.size, len(workers))) + 1).astype(int)
        check_pwls_memory(client, int(frames.size), geometry, grid)
        self.parts = [
            client.submit(
                ViewPart,
                os.fspath(path),
                frames[a:b],
                int(a),
                grid,
                geometry[a:b],
                subsets,
                chunk_views,
                device,
                key=f"{self._key}-part{i}",
                pure=False,
                workers=[workers[i]],
                allow_other_workers=True,
            )
            for i, (a, b) in enumerate(itertools.pairwise(bounds))
        ]
        self._bounds = [int(b) for b in bounds]
        # the workers that held each part when last seen; before the first look, the worker each was sent to (a part
        # not yet read when that worker dies is read elsewhere, and said so, as one already read is)
        self._held: list[set[str]] = [{str(workers[i])} for i in range(len(self.parts))]
        self._checked = 0.0

    def _next_key(self, what: str) -> str:
        self._calls += 1
        return f"{self._key}-{what}{self._calls}"

    def curvature(self, out: NDArray[np.float32]) -> None:
        """Add ``A^T (w * A 1)`` of every part into the padded ``out``."""

        def submit(key: str) -> list[Any]:
            return [
                self.client.submit(_part_curvature, p, key=f"{key}-{i}", pure=False) for i, p in enumerate(self.parts)
            ]

        out += self._run_step("curvature", submit)

    def _run_step(self, what: str, submit: Callable[[str], list[Any]]) -> Any:
        """The sum of the tasks ``submit(key)`` makes. When a worker dies with work of the step (a part's views, the
        iterate), the step runs again on the workers left (Dask reads lost views again) up to :data:`STEP_TRIES`
        times; a scheduler gone or a part that fails ends it with :class:`ClusterError`."""
        for attempt in range(1, STEP_TRIES + 1):
            key = self._next_key(what)
            try:
                return _sum_on_workers(self.client, submit(key), self.what, key)
            except WorkLostError:
                if attempt == STEP_TRIES or not self._scheduler_answers():
                    raise
                self._checked = 0.0
                self._check_parts()
                log.warning("a Dask worker died during a PWLS step; the step runs again on the workers left")
        raise AssertionError("unreachable")  # pragma: no cover - the loop returns or raises

    def _scheduler_answers(self) -> bool:
        """Whether the scheduler still answers (a worker died, not the cluster)."""
        try:
            return bool(self.client.ncores())
        except Exception:  # noqa: BLE001 - any failure to reach it is the same answer
            return False

    def _check_parts(self) -> None:
        """Say (once per loss, at most once a second) when a worker holding views has died: Dask reads those views
        again on a live worker, which costs time, not the image."""
        now = time.monotonic()
        if now - self._checked < LOSS_CHECK_S:
            return
        self._checked = now
        try:
            holders = self.client.who_has(self.parts)
        except Exception:  # noqa: BLE001 - a cluster out of touch fails the next step with its own sentence
            return
        now_at = [set(holders.get(p.key) or ()) for p in self.parts]
        # lost: none of the workers that held it holds it now (it is being read again, or was, elsewhere)
        lost = [
            i for i, (before, now_) in enumerate(zip(self._held, now_at, strict=True)) if before and not before & now_
        ]
        self._held = [now_ or before for before, now_ in zip(self._held, now_at, strict=True)]
        if lost:
            log.warning(
                "a Dask worker holding %s died (killed, or out of memory); those views are read again on a live worker",
                ", ".join(f"views {self._bounds[i]}-{self._bounds[i + 1] - 1}" for i in lost),
            )

    def _send_iterate(self, xp: NDArray[np.float32], tries: int = 3) -> Any:
        """The iterate on every worker. A worker dying while it is sent leaves Dask with a stale list of workers
        (it fails with a ValueError), so the send is tried again on the workers left; a cluster that stays out of
        reach fails with a sentence."""
        for _ in range(tries - 1):
            try:
                return self.client.scatter(xp, broadcast=True, hash=False, timeout=60)
            except Exception as exc:  # noqa: BLE001 - a worker gone mid-send: the workers left may take it
                log.warning("sending the iterate to the workers failed (%s); trying again", exc)
                time.sleep(1.0)
        try:
            return self.client.scatter(xp, broadcast=True, hash=False, timeout=60)
        except Exception as exc:  # noqa: BLE001 - a scheduler or workers gone: say so rather than wait
            raise ClusterError(
                f"the cluster lost {self.what}: cannot send the iterate to the workers ({exc})"
            ) from None

    def gradient(self, xp: NDArray[np.float32], subset: int, out: NDArray[np.float32] | None) -> float:
        """Subset ``subset``'s data term at ``xp`` summed over the parts; its gradient added into ``out``."""
        self._check_parts()
        sent: list[Any] = []  # the iterate on the workers, dropped when the step ends

        def submit(key: str) -> list[Any]:
            sent[:] = [self._send_iterate(xp)]  # again each try: a dead worker may have held the only copy
            return [
                self.client.submit(_part_gradient, p, sent[0], subset, out is not None, key=f"{key}-{i}", pure=False)
                for i, p in enumerate(self.parts)
            ]

        try:
            total = self._run_step(f"subset{subset}-", submit)
        finally:
            sent.clear()  # the workers may drop the iterate
        if out is not None:
            out += total[0]
        return float(total[-1])

    def close(self) -> None:
        """Release the parts (the workers free their views)."""
        try:
            self.client.cancel(self.parts)
        except Exception:  # noqa: BLE001 - a cluster already gone holds nothing
            pass
        self.parts = []

    def __enter__(self) -> ClusterData:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def pwls_on_cluster(
    client: Any,
    path: str | os.PathLike[str],
    frames: NDArray[np.intp],
    grid: VolumeGrid,
    geometry: ViewGeometry,
    *,
    x0: NDArray[np.float32] | None = None,
    subsets: int = 1,
    beta: float = DEFAULT_BETA,
    iterations: int = 50,
    neighbourhood: int = 1,
    momentum: bool = False,
    final_cost: bool = False,
    curvature: dict[str, Any] | None = None,
    progress: ProgressCallback | None = None,
    workers_timeout_s: float = 30.0,
    device: str = "auto",
) -> PwlsResult:
    """PWLS (:func:`recon.pwls.pwls_sps`) of the projections ``frames`` of the scan at ``path`` with the views
    spread over the workers of ``client``; ``x0`` as there (padded: updated in place); ``curvature``: the
    ``data_curvature`` / ``keep_data_curvature`` arguments of :func:`recon.pwls.pwls_solve`. Each worker projects
    its views on ``device`` as it resolves it (``auto``: its GPU when it has a usable one); the steps are taken here."""
    with ClusterData(
        client, path, frames, grid, geometry, subsets=subsets, workers_timeout_s=workers_timeout_s, device=device
    ) as data:
        return pwls_solve(
            data,
            beta=beta,
            iterations=iterations,
            x0=x0,
            neighbourhood=neighbourhood,
            momentum=momentum,
            final_cost=final_cost,
            progress=progress,
            **(curvature or {}),
        )


__all__ = [
    "PARTS_PER_WORKER",
    "ClusterData",
    "ClusterError",
    "ViewPart",
    "WorkLostError",
    "check_pwls_memory",
    "fdk_on_cluster",
    "pwls_on_cluster",
]
