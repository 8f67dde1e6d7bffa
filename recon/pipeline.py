"""Reconstruct a scan file end to end: read, check, reconstruct, store ``/recon/<name>``, export."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_args

import numpy as np
import psutil
from numpy.typing import NDArray
from pydantic import ValidationError

from orbitct.compiletime import CompileClock
from orbitct.geometry import ViewGeometry, VolumeGrid
from orbitct.progress import ProgressCallback, describe_seconds, report, report_expected
from orbitct.scanfile import ImageKey, ScanFile
from orbitct.verdict import Verdict
from recon.curvature import curvature_key
from recon.curvature import load as load_curvature
from recon.curvature import save as save_curvature
from recon.device import describe_device, from_the_gpu, make_projector, resolve_device, simulated
from recon.errors import (
    BadFramesError,
    FailedGeometryError,
    GeometryMissingError,
    MemoryBudgetError,
    ReconError,
    ReconExistsError,
    TooLongError,
)
from recon.estimate import reconstruction_seconds
from recon.export import FORMATS, export_volume
from recon.fdk import fdk
from recon.fitgrid import object_grid
from recon.grid import check_fov, grid_for_geometry
from recon.mar import (
    add_metal_back,
    fill_traces_normalized,
    metal_in_volume,
    tissue_prior,
    traces_by_reprojection,
    traces_by_threshold,
)
from recon.operator import pad_volume
from recon.options import GeometryName, ReconstructionOptions, StreamMode
from recon.pwls import pwls_sps, statistical_weights
from recon.stack import FileLineIntegrals, FileWeights

GEOMETRIES: tuple[str, ...] = get_args(GeometryName)
#: where a reconstruction split across Dask workers ran, by the device asked for
CLUSTER_DEVICES = {
    "auto": "Dask workers (each on its GPU when it has a usable one, else on its CPU)",
    "cpu": "Dask workers (their CPUs)",
    "cuda": "Dask workers (their GPUs)",
}
STREAM_MODES: tuple[str, ...] = get_args(StreamMode)


@dataclass
class ReconResult:
    """What :func:`reconstruct_scan` produced and where it is stored."""

    name: str
    path: Path
    algorithm: str
    geometry: str
    volume_shape: tuple[int, int, int]
    voxel_mm: tuple[float, float, float]
    origin_mm: tuple[float, float, float]
    cost: list[float] = field(default_factory=list)
    elapsed_s: float = 0.0
    exported: list[Path] = field(default_factory=list)
    params: dict[str, Any] = field(default_factory=dict)
    volume: NDArray[np.float32] | None = field(default=None, repr=False)
    warnings: list[str] = field(default_factory=list)
    compile_s: float = 0.0  # numba compiling its kernels on first use (after installation); not in elapsed_s

    @property
    def verdict(self) -> Verdict:
        """Its quality verdict: passed, or passed with its warnings (a failure raises instead)."""
        return Verdict(warnings=tuple(self.warnings))

    @property
    def grid(self) -> VolumeGrid:
        """The grid the volume is sampled on."""
        return VolumeGrid(self.volume_shape, self.voxel_mm, self.origin_mm)


def estimate_bytes(
    algorithm: str, grid: VolumeGrid, n_views: int, rows: int, cols: int, mar: bool, stream: str = "memory"
) -> int:
    """Peak working memory (bytes) a reconstruction needs, before anything is allocated.

    ``stream`` 'file' is PWLS reading projections and weights from the scan file each iteration;
    'memory' holds both in memory (FDK always streams unless MAR needs the projections at hand); 'cluster' keeps
    them on a Dask cluster's workers (:mod:`recon.cluster`), this process holding only volumes.
    """
    nz, ny, nx = grid.shape
    vol = grid.nbytes
    padded = 4 * (nz + 2) * (ny + 2) * (nx + 2)
    proj = 4 * n_views * rows * cols
    fdk_chunk = 4 * 4 * min(8, n_views) * (rows + 2) * (cols + 2)  # padded buffer and FFT temporaries
    pwls_chunk = 3 * 4 * min(8, n_views) * rows * cols  # residual, projections, weights
    mar_extra = 2 * proj + proj // 4 + 3 * vol if mar else 0
    if algorithm == "fdk":
        total = vol + fdk_chunk + (proj + mar_extra if mar else 0)
    elif stream == "cluster":  # the views stay on the workers: here the iterate, its momentum, gradient, surrogate
        total = vol + 4 * padded
    elif stream == "file":
        # FDK into the padded iterate, then iterate + gradient + surrogate denominators
        total = max(padded + fdk_chunk, 3 * padded + pwls_chunk)
    else:
        total = 2 * proj + max(padded + fdk_chunk, 3 * padded + pwls_chunk) + mar_extra
    return int(total * 1.1)


def choose_stream(stream: str, algorithm: str, grid: VolumeGrid, n_views: int, rows: int, cols: int, mar: bool) -> str:
    """'memory' or 'file' for a PWLS run: 'auto' keeps the projections in memory while they fit in half the free memory."""
    if stream not in STREAM_MODES:
        raise ReconError(f"stream must be one of {STREAM_MODES}, got {stream!r}")
    if algorithm != "pwls":
        return "memory"
    if mar:
        if stream == "file":
            raise ReconError(
                "metal artifact reduction needs the corrected projections in memory; "
                "use stream 'auto' or 'memory' with mar"
            )
        return "memory"
    if stream != "auto":
        return stream
    needed = estimate_bytes(algorithm, grid, n_views, rows, cols, False, "memory")
    return "memory" if needed <= 0.5 * psutil.virtual_memory().available else "file"


def check_memory(needed: int, what: str) -> None:
    """Raise :class:`MemoryBudgetError` when ``needed`` bytes exceed 90 % of the available memory."""
    avail = int(psutil.virtual_memory().available)
    if needed > 0.9 * avail:
        raise MemoryBudgetError(
            f"{what} needs about {needed / 2**30:.2f} GiB but only {avail / 2**30:.2f} GiB is available; "
            "use a larger --voxel-mm, a smaller --shape, or fewer views"
        )


def _views(scan: ScanFile, geometry: str) -> tuple[NDArray[np.intp], ViewGeometry, int]:
    if geometry not in GEOMETRIES:
        raise ReconError(f"geometry must be one of {GEOMETRIES}, got {geometry!r}")
    if not scan.has_geometry(geometry):
        present = [g for g in GEOMETRIES if scan.has_geometry(g)]
        hint = " (run `orbitct calibrate` first)" if geometry == "calibrated" else ""
        raise GeometryMissingError(f"{scan.path}: has no {geometry} geometry{hint}; present: {present}")
    frames = scan.projection_indices
    if frames.size == 0:
        raise ReconError(f"{scan.path}: has no projection frames")
    g = scan.geometry(geometry)[frames]
    ok = g.valid
    if not ok.any():
        raise GeometryMissingError(f"{scan.path}: the {geometry} geometry has no finite projection views")
    return frames[ok], g[np.flatnonzero(ok)], int((~ok).sum())


def failed_geometry_reasons(scan: ScanFile, geometry: str) -> list[str] | None:
    """Why the scan's calibrated geometry failed its quality check, or None when it did not (or is not used)."""
    if geometry != "calibrated" or "geometry/calibrated" not in scan.h5:
        return None
    attrs = scan.h5["geometry/calibrated"].attrs
    if str(attrs.get("quality", "")) != "failed":
        return None
    try:
        return [str(r) for r in json.loads(str(attrs.get("quality_reasons_json", "[]")))]
    except ValueError:
        return []


def _geometry_verdict(scan: ScanFile, geometry: str, accepted: bool) -> list[str]:
    """The warning a volume from a failed calibrated geometry carries; that geometry refused unless ``accepted``."""
    reasons = failed_geometry_reasons(scan, geometry)
    if reasons is None:
        return []
    if not accepted:
        raise FailedGeometryError(scan.path.name, reasons)
    why = f" ({'; '.join(reasons)})" if reasons else ""
    return [
        f"made from a calibrated geometry that failed its quality check, by explicit override{why}; the volume "
        "inherits those views' errors"
    ]


def _load(
    scan: ScanFile, frames: NDArray[np.intp], with_weights: bool, progress: ProgressCallback | None
) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    det = scan.panel
    li = np.empty((frames.size,) + det.shape, np.float32)
    w = np.empty_like(li) if with_weights else None
    dark, flat = scan.dark_flat()
    for k, i in enumerate(frames):
        li[k] = scan.line_integrals(int(i))
        if w is not None:
            w[k] = statistical_weights(scan.frames[int(i)], dark, flat)
        if k % 8 == 7 or k == frames.size - 1:
            report(progress, "load", k + 1, frames.size, "projections")
    return li, w


def _curvature(
    scan: ScanFile, frames: NDArray[np.intp], geom: ViewGeometry, grid: VolumeGrid, extra: dict[str, Any]
) -> dict[str, Any]:
    """PWLS's arguments for the data curvature: the cached one for these views, geometry, grid and weights, or a
    callback that caches the one computed; ``extra['curvature']`` says which."""
    key = curvature_key(scan, frames, geom, grid)
    cached = load_curvature(key, grid.shape)
    extra["curvature"] = "reused" if cached is not None else "computed"
    if cached is not None:
        return {"data_curvature": cached}
    return {"keep_data_curvature": lambda d: save_curvature(key, d)}


def _pwls(
    li: Any,
    w: Any,
    grid: VolumeGrid,
    geom: ViewGeometry,
    opts: ReconstructionOptions,
    progress: ProgressCallback | None,
    curvature: dict[str, Any] | None,
    device: str,
) -> tuple[NDArray[np.float32], list[float], float]:
    """FDK into the interior of a padded volume, then PWLS as ``opts`` say updating that volume in place
    (``curvature``: the data curvature's arguments, from :func:`_curvature`; ``device``: cpu or cuda)."""
    A = make_projector(grid, geom, device)
    xp = np.zeros(A.padded_shape, np.float32)
    fdk(li, grid, geom, window=opts.window, out=xp[1:-1, 1:-1, 1:-1], progress=progress, device=device)
    res = pwls_sps(
        A,
        li,
        w,
        beta=opts.beta,
        iterations=opts.iterations,
        x0=xp,
        neighbourhood=opts.neighbourhood,
        subsets=opts.subsets,
        momentum=opts.momentum,
        final_cost=opts.final_cost,
        progress=progress,
        **(curvature or {}),
    )
    return res.volume, res.cost, res.beta_abs


def _device_memory(device: str) -> dict[str, int]:
    """The peak GPU memory of a reconstruction that ran on one (nothing for the CPU)."""
    if device != "cuda":
        return {}
    from recon.cuda import peak_bytes

    return {"device_peak_bytes": peak_bytes()}


def checked_options(options: ReconstructionOptions | None, values: dict[str, Any]) -> ReconstructionOptions:
    """``options`` with ``values`` laid over them, validated; a :class:`ReconError` naming each bad option."""
    if options is not None and not values:
        return options  # validated when it was made (the model is frozen)
    merged = {**(options.model_dump() if options is not None else {}), **values}
    try:
        return ReconstructionOptions.model_validate(merged)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'options'}: {e['msg']}" for e in exc.errors())
        raise ReconError(f"invalid reconstruction options: {problems}") from None


def reconstruct_scan(
    path: str | os.PathLike[str],
    options: ReconstructionOptions | None = None,
    *,
    export: str | list[str] | None = None,
    out_dir: str | os.PathLike[str] | None = None,
    progress: ProgressCallback | None = None,
    grid: VolumeGrid | None = None,
    cluster: Any | None = None,
    **values: Any,
) -> ReconResult:
    """Reconstruct ``path`` as ``options`` say (:class:`~recon.options.ReconstructionOptions`; keyword ``values``
    are laid over them) and store it as ``/recon/<name>`` in the scan file.

    PWLS data stream (``stream``): 'memory' loads projections and weights once, 'file' recomputes them from the
    scan file chunk by chunk every iteration (three volumes of memory, slower), 'auto' picks 'memory' while it fits
    in half the free memory. A reconstruction of the same name is replaced only with ``overwrite``
    (:class:`ReconExistsError` otherwise, before any work). One estimated to take longer than ``max_minutes``
    (:mod:`recon.estimate`) raises :class:`TooLongError` before anything large is allocated. Without ``shape`` the
    grid is fitted to the object (``fit='object'``, :func:`recon.fitgrid.object_grid`) or covers the whole field of
    view (``fit='fov'``); ``grid`` gives the grid itself (another reconstruction's, to compare). ``export``: formats
    among :data:`recon.export.FORMATS`, written to ``out_dir`` (default: beside the scan). ``cluster``: a
    ``dask.distributed.Client`` whose workers share the views of FDK and of PWLS (:mod:`recon.cluster`; they read the
    scan file at the same path; ``stream`` does not apply); metal artefact reduction runs here. Kernels compiled on
    first use after installation are timed apart (``compile_s``), not in ``elapsed_s``.
    """
    with CompileClock() as clock:
        try:
            return _reconstruct(
                path,
                options,
                export=export,
                out_dir=out_dir,
                progress=progress,
                grid=grid,
                cluster=cluster,
                clock=clock,
                **values,
            )
        except Exception as exc:
            if not from_the_gpu(exc):
                raise
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise ReconError(f"the GPU failed ({first}); --device cpu reconstructs on the CPU") from exc


def _reconstruct(
    path: str | os.PathLike[str],
    options: ReconstructionOptions | None,
    *,
    export: str | list[str] | None,
    out_dir: str | os.PathLike[str] | None,
    progress: ProgressCallback | None,
    grid: VolumeGrid | None,
    cluster: Any | None,
    clock: CompileClock,
    **values: Any,
) -> ReconResult:
    t0 = time.perf_counter()
    opts = checked_options(options, values)
    algorithm, geometry, iterations, beta = opts.algorithm, opts.geometry, opts.iterations, opts.beta
    window, subsets, neighbourhood, momentum = opts.window, opts.subsets, opts.neighbourhood, opts.momentum
    metal_mu, mar_threshold = opts.metal_mu_per_mm, opts.mar_threshold
    mar_method = opts.mar_method if opts.mar else None
    formats = [export] if isinstance(export, str) else list(export or [])
    if any(f not in FORMATS for f in formats):
        raise ReconError(f"export formats must be among {FORMATS}, got {formats}")
    shape = (opts.shape[0], opts.shape[1], opts.shape[2]) if opts.shape is not None else None  # three: validated
    on_cluster = cluster is not None and not mar_method
    # before any work: a missing GPU is said first (on a cluster each worker resolves the device for itself)
    device = "cpu" if on_cluster else resolve_device(opts.device)
    if device == "cuda":
        from recon.cuda import reset_peak

        reset_peak()
    name = opts.recon_name
    with ScanFile(path, "r") as scan:  # read-only while computing: other readers may hold the file
        scan.refuse_if_acquiring()  # before any work: the result could not be stored
        if name in scan.recon_names() and not opts.overwrite:
            raise ReconExistsError(scan.path, name)
        frames, geom, dropped = _views(scan, geometry)
        warnings = [*scan.warnings, *_geometry_verdict(scan, geometry, opts.accept_failed_geometry)]
        if dropped:
            warnings.append(f"{dropped} view(s) without a finite {geometry} geometry were left out")
        fitted = grid is None and shape is None and opts.fit == "object"
        grid_note = "as given" if grid is not None or shape is not None else "the whole field of view"
        grid = grid if grid is not None else grid_for_geometry(geom, voxel_mm=opts.voxel_mm, shape=shape)
        fov_fraction = check_fov(grid, geom)
        det = geom.panel
        mode = (
            "cluster"
            if cluster is not None and algorithm == "pwls" and not mar_method
            else choose_stream(opts.stream, algorithm, grid, frames.size, det.rows, det.cols, bool(mar_method))
        )
        check_memory(
            estimate_bytes(algorithm, grid, frames.size, det.rows, det.cols, bool(mar_method), mode),
            f"{scan.path}: {algorithm} of {frames.size} views of {det.rows} x {det.cols} pixels onto "
            f"{grid.shape} voxels",
        )
        needed = np.union1d(frames, np.flatnonzero(np.isin(scan.image_key, (ImageKey.DARK, ImageKey.FLAT))))
        problems = scan.frame_problems(needed)  # after the memory check: it reads every frame it needs
        if problems:
            raise BadFramesError(scan.path, problems, needed.size)
        if fitted:
            report(progress, "grid", 0, 1, "finding the object")
            grid, grid_note = object_grid(FileLineIntegrals(scan, frames), geom, grid)
            report(progress, "grid", 1, 1, grid_note)
        estimated_s = reconstruction_seconds(
            algorithm,
            grid,
            int(frames.size),
            det.rows,
            det.cols,
            iterations if algorithm == "pwls" else 0,
            opts.final_cost,
            geometry=geom,
            device="cpu" if simulated() else device,  # the CUDA simulator's speed says nothing of a GPU's
        )
        max_seconds = opts.max_seconds
        if max_seconds is not None and estimated_s > max_seconds:
            raise TooLongError(
                f"{scan.path}: {algorithm} of {frames.size} views of {det.rows} x {det.cols} pixels onto {grid.shape} "
                f"voxels of {grid.voxel_mm[0]:g} mm is estimated to take {describe_seconds(estimated_s)} on this "
                f"machine now, more than the limit of {describe_seconds(max_seconds)}; a larger voxel size, a smaller "
                "shape or (PWLS) ordered subsets with momentum and fewer iterations are faster",
                estimated_s,
            )
        report_expected(progress, "reconstruction", estimated_s)
        cost: list[float] = []
        extra: dict[str, Any] = {}
        if on_cluster and cluster is not None:
            from recon.cluster import check_pwls_memory, fdk_on_cluster, pwls_on_cluster

            if algorithm == "pwls":
                check_pwls_memory(cluster, int(frames.size), geom, grid)  # before the FDK start image runs there
            vol = fdk_on_cluster(
                cluster, scan.path, frames, grid, geom, window=window, progress=progress, device=opts.device
            )
            extra.update(cluster_workers=len(cluster.scheduler_info()["workers"]))
            if algorithm == "pwls":
                res = pwls_on_cluster(
                    cluster,
                    scan.path,
                    frames,
                    grid,
                    geom,
                    x0=pad_volume(vol),
                    subsets=subsets,
                    beta=beta,
                    iterations=iterations,
                    neighbourhood=neighbourhood,
                    momentum=momentum,
                    final_cost=opts.final_cost,
                    curvature=_curvature(scan, frames, geom, grid, extra),
                    progress=progress,
                    device=opts.device,
                )
                vol, cost = res.volume, res.cost
                extra.update(beta_abs=res.beta_abs, stream="cluster")
        elif algorithm == "fdk" and not mar_method:
            vol = fdk(FileLineIntegrals(scan, frames), grid, geom, window=window, progress=progress, device=device)
        elif mode == "file":
            vol, cost, beta_abs = _pwls(
                FileLineIntegrals(scan, frames),
                FileWeights(scan, frames),
                grid,
                geom,
                opts,
                progress,
                _curvature(scan, frames, geom, grid, extra),
                device,
            )
            extra.update(beta_abs=beta_abs, stream="file")
        else:
            li, w = _load(scan, frames, algorithm == "pwls", progress)
            metal = None
            if mar_method:
                first = fdk(li, grid, geom, window=window, device=device)
                metal = metal_in_volume(first, metal_mu)
                A = make_projector(grid, geom, device)
                traces = (
                    traces_by_threshold(li, mar_threshold)
                    if mar_method == "threshold"
                    else traces_by_reprojection(A, metal)
                )
                li = fill_traces_normalized(li, traces, A(tissue_prior(first, metal)))
                if w is not None:
                    w = np.where(traces, np.exp(-li), w).astype(np.float32)
                extra.update(mar_method=mar_method, metal_voxels=int(metal.sum()), trace_fraction=float(traces.mean()))
                report(progress, "mar", 1, 1, f"{int(metal.sum())} metal voxels")
            if algorithm == "pwls":
                curvature = None if metal is not None else _curvature(scan, frames, geom, grid, extra)
                vol, cost, beta_abs = _pwls(li, w, grid, geom, opts, progress, curvature, device)
                extra.update(beta_abs=beta_abs, stream="memory")
            else:
                vol = fdk(li, grid, geom, window=window, progress=progress, device=device)
            if metal is not None:
                vol = add_metal_back(vol, first, metal)
        elapsed = time.perf_counter() - t0 - clock.seconds  # compiling kernels on first use: apart
        params = {
            "window": window,
            "views": int(frames.size),
            "views_dropped_nonfinite": dropped,
            "fov_fraction": fov_fraction,
            "grid": grid.to_json(),
            "grid_choice": grid_note,
            "estimated_s": estimated_s,
            "compile_s": clock.seconds,
            "geometry_override": bool(failed_geometry_reasons(scan, geometry) is not None),
            "device": CLUSTER_DEVICES[opts.device] if on_cluster else describe_device(device),
            **extra,
            **_device_memory(device),
        }
        if algorithm == "pwls":
            params.update(
                beta=beta,
                neighbourhood=neighbourhood,
                subsets=subsets,
                momentum=momentum,
                cost=cost,
                final_cost=opts.final_cost,
            )
        scan_path = scan.path
    with ScanFile(scan_path, "r+") as out:
        out.write_recon(
            name,
            vol,
            voxel_mm=grid.voxel_mm,
            origin_mm=grid.origin_mm,
            algorithm=algorithm,
            geometry=geometry,
            iterations=iterations if algorithm == "pwls" else 0,
            elapsed_s=elapsed,
            params=params,
            overwrite=opts.overwrite,
            verdict=Verdict(warnings=tuple(warnings)),
        )
    exported: list[Path] = []
    if formats:
        base = Path(out_dir) if out_dir is not None else scan_path.parent
        exported = export_volume(vol, grid, formats, base / f"{scan_path.stem}_{name}")
    return ReconResult(
        name,
        scan_path,
        algorithm,
        geometry,
        grid.shape,
        grid.voxel_mm,
        grid.origin_mm,
        cost,
        elapsed,
        exported,
        params,
        vol,
        warnings,
        clock.seconds,
    )


def compare_reconstructions(path: str | os.PathLike[str], names: Sequence[str], out: str | os.PathLike[str]) -> Path:
    """A PNG of reconstructions of one scan side by side, a row each, in one grey window (the first one's), each
    row named by its algorithm and geometry, the figure by the scan file and its orbit. They must share a grid."""
    from recon.export import export_comparison

    rows: list[tuple[str, NDArray[np.float32]]] = []
    grid = None
    with ScanFile(path) as scan:
        orbit, params = scan.orbit
        for name in names:
            vol, attrs = scan.read_recon(name)
            g = VolumeGrid(vol.shape, tuple(attrs["voxel_mm"]), tuple(attrs["origin_mm"]))
            if grid is not None and g != grid:
                raise ReconError(
                    f"{scan.path}: /recon/{name} is on another grid than /recon/{names[0]}; "
                    "compare reconstructions made with the same --shape and --voxel-mm"
                )
            grid = g
            rows.append((f"{attrs['algorithm'].upper()}, {attrs['geometry']} geometry", vol))
        title = f"{scan.path.name}: {orbit or 'orbit unknown'}, {int(scan.projection_indices.size)} projections"
    assert grid is not None
    return export_comparison(rows, grid, Path(out), title)
