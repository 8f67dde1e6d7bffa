"""``calibrate_scan``: detect BBs in a scan file, identify them, estimate the geometry, write the results."""

from __future__ import annotations

import os
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from calib.detect import N_FIELDS, FrameDetector, _refine, detection_spread, settings_for
from calib.errors import (
    BadFramesError,
    FrameTooLargeError,
    NoMarkersError,
    NoNominalGeometryError,
    NoProjectionsError,
    OptionError,
)
from calib.evaluate import fov_points, true_corrections
from calib.identify import identify
from calib.model import ViewModel, ViewState
from calib.options import (
    DEFAULT_JITTER_MM,
    LAST_RESORT_JITTER_MM,
    METHODS,
    REASSIGN_JITTER_MM,
    RECOVERY_JITTER_MM,
    CalibrationOptions,
    checked_options,
)
from calib.quality import (
    MIN_OWN_BBS,
    OWN,
    STATUS_CODES,
    judge,
)
from calib.rays import rpe_per_frame
from calib.refine import (
    Polish,
    estimate,
    estimate_again,
    jumped_views_again,
    merge_twins,
    mild_misfits_only,
    min_observations,
    reassign,
    recover_missed_bbs,
    residual_px,
    sparse_views_again,
    split_merged,
)
from calib.result import CalibrationResult, IterationStats, iteration_stats
from calib.scale import find_scale_bar, rescaled_views
from calib.search import FULL_EVERY, LAG, SearchPlan, Windows
from calib.track import TrackingSettings, link_fragments
from orbitct.compiletime import CompileClock
from orbitct.geometry import ViewGeometry
from orbitct.progress import ProgressCallback, report, report_expected
from orbitct.scanfile import (
    FrameReader,
    ImageKey,
    ScanFile,
    describe_frame_problems,
    frame_problem,
    write_linked_scan,
)
from orbitct.scanfile.reader import FRAME_COPIES

#: rounds of placing views whose frame jumped (:func:`calib.refine.jumped_views_again`)
JUMPED_ROUNDS = 3


def motion_px(nominal: ViewGeometry) -> float:
    """95th percentile of how far points in the field of view move between neighbouring projections (px)."""
    if nominal.n_views < 2:
        return 0.0
    uv = nominal.project(fov_points(nominal, 4))
    step = np.linalg.norm(np.diff(uv, axis=0), axis=-1)
    return float(np.nanpercentile(step, 95))


def _detect(
    sf: ScanFile,
    proj: NDArray[np.intp],
    nominal: ViewGeometry,
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    clock: CompileClock,
    seeds_uv: Any = None,
    workers: int = 2,
) -> tuple[list[NDArray[np.float64]], float, float]:
    """Candidates of every projection, streamed frame by frame (``workers`` threads; ``seeds_uv``: BB positions
    known in the first projection); also BB diameter (mm and px)."""
    det = sf.panel
    mag = float(np.median(nominal.sdd / nominal.sod()))
    pitch = float(np.sqrt(det.pitch_col * det.pitch_row))
    dark, flat = sf.dark_flat()
    diameter_mm = opt.diameter_mm if opt.diameter_mm is not None else sf.marker_diameter_mm
    if diameter_mm is None:
        diameter_mm = _estimate_diameter_mm(sf, proj, dark, flat, mag, pitch, opt)
    d_px = projected_diameter_px(nominal, diameter_mm)
    fd = frame_detector(dark, flat, d_px, opt, two_flats(sf))
    total = len(proj)
    step = max(1, total // 100)
    cands: list[NDArray[np.float64]] = [np.zeros((0, N_FIELDS))] * total
    problems: dict[int, str] = {}

    plan = SearchPlan.for_scan(d_px, motion_px(nominal), opt.jitter_mm * d_px / diameter_mm, opt.bb_search)
    floors = np.full(total, np.nan)  # per frame searched whole, the weakest score it kept (NaN: searched round)

    def checked(buf: NDArray[Any], windows: Windows | None = None) -> tuple[NDArray[Any], float]:
        """The frame's candidates and floor (:meth:`SearchPlan.search`); a frame that cannot be used yields the
        reason instead."""
        why = frame_problem(buf, projection=True)
        if why is not None:
            return np.array([why], dtype=object), 0.0
        found = plan.search(fd, buf, windows)
        return found.records, found.floor

    def take(m: int, found: tuple[NDArray[Any], float]) -> None:
        c, floors[m] = found
        if c.dtype == object:
            problems[int(proj[m])] = str(c[0])
            c = np.zeros((0, N_FIELDS))
        cands[m] = c

    def read_and_check(m: int, windows: Windows | None = None) -> tuple[NDArray[Any], float]:
        return checked(frames.read(int(proj[m])), windows)

    # the workers read their frames (straight from the file: the GIL is free while they do) and run the GIL-free
    # kernels. A predicted search takes frame n - LAG's candidates before frame n is sent; the frames it searches
    # whole in any case are sent EARLY frames before their turn, so that the frames whose windows come from them
    # do not wait behind them
    ahead = LAG - 1 if plan.predicted else 2 * max(1, workers)
    begun = started = time.perf_counter()
    compiled_before = compiled = clock.seconds
    with FrameReader(sf.frames) as frames, ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        pending: deque[tuple[int, Future[tuple[NDArray[Any], float]]]] = deque()
        early: dict[int, Future[tuple[NDArray[Any], float]]] = {}
        for n in range(total):
            if n == 4:  # timed from here: the first frames set things up (noise level, kernels loaded)
                started, compiled = time.perf_counter(), clock.seconds
            elif n == 4 + FRAMES_TIMED and total >= 2 * n:  # these frames show this machine's (and disk's) pace
                per_frame = (time.perf_counter() - started - (clock.seconds - compiled)) / FRAMES_TIMED
                so_far = time.perf_counter() - begun - (clock.seconds - compiled_before)
                report_expected(progress, "calibration", so_far + calibration_seconds(total - n, per_frame))
            if n == 0:
                buf = frames.read(int(proj[0]))
                c, floor = checked(buf)  # also fixes the noise level used for every frame
                if seeds_uv is not None and c.dtype != object:
                    c = np.concatenate([_seed_records(buf, fd, np.asarray(seeds_uv, float)), c])
                take(0, (c, floor))
                continue
            if plan.predicted and n + EARLY < total and plan.whole(n + EARLY):
                early[n + EARLY] = pool.submit(read_and_check, n + EARLY)
            fut = early.pop(n, None)
            pending.append((n, fut or pool.submit(read_and_check, n, plan.windows(n, cands, floors))))
            while len(pending) > ahead or (pending and pending[0][1].done()):
                m, fut = pending.popleft()
                take(m, fut.result())
                if m % step == 0:
                    report(progress, "detect", m + 1, total, "", candidates=float(len(cands[m])))
        for m, fut in pending:
            take(m, fut.result())
    if problems:
        raise BadFramesError(
            f"{sf.path}: {len(problems)} of {total} projections are unusable: "
            f"{describe_frame_problems(problems)}; a geometry fitted to them would be wrong, so none "
            "is stored"
        )
    windowed = f"{int(np.isnan(floors).sum())} of {total} searched round the BBs found" if plan.predicted else ""
    report(progress, "detect", total, total, windowed)
    return cands, float(diameter_mm), d_px


FRAMES_TIMED = 16  # frames read and searched before a calibration says how long it takes
EARLY = 2 * FULL_EVERY  # how many frames before its turn a frame searched whole in any case is sent
SOLVE_S = 0.6  # identification, estimation and checks: 0.2-1.4 s on the 2-core reference, whatever the view count


def calibration_seconds(n_projections: int, per_frame_s: float) -> float:
    """Expected seconds of a calibration's rest: ``n_projections`` read and searched at the pace measured on its
    first frames (this machine, its disk, now), then the solve. The solve's share is a typical figure, not a
    measurement: it depends on how hard the BBs are to follow (metal, clutter, large motion between views)."""
    return n_projections * per_frame_s + SOLVE_S


def frame_detector(
    dark: NDArray[np.float32],
    flat: NDArray[np.float32],
    d_px: float,
    opt: CalibrationOptions,
    flats: tuple[NDArray[Any], NDArray[Any]] | None = None,
) -> FrameDetector:
    """The detector every projection of a scan goes through (BB size in pixels, the options' threshold; with two
    single ``flats``, the panel's noise correlation measured)."""
    settings = settings_for(d_px, dark.shape)
    settings.k_sigma, settings.max_candidates = opt.k_sigma, opt.max_candidates
    fd = FrameDetector(dark, flat, settings)
    if flats is not None:
        fd.measure_noise_correlation(*flats)
    return fd


def two_flats(sf: ScanFile) -> tuple[NDArray[Any], NDArray[Any]] | None:
    """The scan's first two flat frames (None when it has fewer)."""
    flats = np.flatnonzero(sf.image_key == ImageKey.FLAT)
    if flats.size < 2:
        return None
    return np.asarray(sf.frames[int(flats[0])]), np.asarray(sf.frames[int(flats[1])])


def _seed_records(raw: NDArray[Any], fd: FrameDetector, seeds: NDArray[np.float64]) -> NDArray[np.float64]:
    if seeds.ndim != 2 or seeds.shape[1] != 2:
        raise OptionError(f"seeds_uv must have shape (K, 2) as (col, row), got {seeds.shape}")
    out = []
    r = 0.5 * fd.settings.diameter_px
    raw = fd.defects.filled(raw)
    for col, row in seeds:
        rec = _refine(raw, fd.dark, fd.den, float(col), float(row), r, fd.half, fd.settings.refine_passes)
        if np.isfinite(rec[0]):
            full = np.full(N_FIELDS, np.nan)
            full[0:2] = rec[0:2]
            full[2] = np.inf
            full[3], full[4], full[5], full[6] = rec[2], r, 1.0, 0.0
            out.append(full)
    return np.array(out).reshape(-1, N_FIELDS)


def _estimate_diameter_mm(
    sf: ScanFile, proj: NDArray[np.intp], dark: Any, flat: Any, mag: float, pitch: float, opt: CalibrationOptions
) -> float:
    """BB diameter from the size of the strongest round blobs in a few frames (two refinements)."""
    guess_mm = 3.0
    sample = proj[np.linspace(0, len(proj) - 1, min(12, len(proj))).astype(int)]
    for _ in range(3):
        d_px = guess_mm * mag / pitch
        fd = FrameDetector(dark, flat, settings_for(d_px, sf.panel.shape))
        radii = []
        for i in sample:
            c = fd.candidates(np.asarray(sf.frames[int(i)]))
            c = c[(c[:, 5] < 1.3)][:8]
            radii.extend(c[:, 4].tolist())
        if not radii:
            raise NoMarkersError(f"{sf.path}: no round blobs found to estimate the BB size; pass diameter_mm")
        guess_mm = float(2.0 * np.median(radii) / 1.1 * pitch / mag)
    return guess_mm


def _check_frame_memory(sf: ScanFile, copies: int = FRAME_COPIES) -> None:
    """Refuse frames too large to process here: detection holds about ``copies`` float64 images per worker."""
    import psutil

    need = sf.panel.rows * sf.panel.cols * 8 * copies
    available = psutil.virtual_memory().available
    if need > available // 2:
        raise FrameTooLargeError(
            f"{sf.path}: a frame of {sf.panel.rows} x {sf.panel.cols} pixels needs about {need / 2**30:.1f} GiB to "
            f"process and {available / 2**30:.1f} GiB is available; refusing before allocating it"
        )


def calibrate_scan(
    path: str | os.PathLike[str],
    *,
    method: str = "bundle",
    out: str | os.PathLike[str] | None = None,
    report_dir: str | os.PathLike[str] | None = None,
    progress: ProgressCallback | None = None,
    seeds_uv: Any = None,
    workers: int = 2,
    **options: Any,
) -> CalibrationResult:
    """Calibrate a scan's geometry from the BBs in its projections and write the results.

    ``options``: the fields of :class:`~calib.options.CalibrationOptions` (as the CLI and the REST API take them);
    ``seeds_uv``: (K, 2) BB positions (col, row) known in the first projection; ``workers``: detection threads."""
    # the linear algebra here is small; BLAS threads would only spin against the detection threads
    with threadpool_limits(limits=1, user_api="blas"), CompileClock() as clock:
        return _calibrate_scan(path, method, out, report_dir, progress, options, clock, seeds_uv, workers)


@dataclass(frozen=True)
class _ScanInputs:
    """What a calibration reads from its scan file besides the frames."""

    target: Path
    proj: NDArray[np.intp]
    nominal_all: ViewGeometry
    truth_all: ViewGeometry | None
    file_warnings: list[str] = field(default_factory=list)  # what the reader ignored in the file, and why

    @property
    def nominal(self) -> ViewGeometry:
        return self.nominal_all[self.proj]


def _read_inputs(sf: ScanFile, target: Path, check_frames: bool = True) -> _ScanInputs:
    """Refuse a scan that cannot be calibrated (before any work); its projections and geometries."""
    sf.refuse_if_acquiring()  # the result could not be stored
    if check_frames:
        _check_frame_memory(sf)
        bad = sf.frame_problems(np.flatnonzero(np.isin(sf.image_key, (ImageKey.DARK, ImageKey.FLAT))))
        if bad:
            raise BadFramesError(
                f"{target}: dark or flat frames are unusable: {describe_frame_problems(bad)}; every "
                "projection is normalised with them"
            )
    proj = sf.projection_indices
    if proj.size == 0:
        raise NoProjectionsError(f"{target}: no projection frames (image_key 0); counts are {sf.count_by_kind()}")
    if not sf.has_geometry("nominal"):
        raise NoNominalGeometryError(f"{target}: no /geometry/nominal; calibration starts from the nominal geometry")
    return _ScanInputs(
        target,
        proj,
        sf.geometry("nominal"),
        sf.geometry("truth") if sf.has_geometry("truth") else None,
        list(sf.warnings),
    )


def projected_diameter_px(nominal: ViewGeometry, diameter_mm: float) -> float:
    """A BB's projected diameter in pixels at the nominal magnification (the median over the views)."""
    return float(np.nanmedian(nominal.projected_size_px(diameter_mm)))


def calibrate_candidates(
    path: str | os.PathLike[str],
    candidates: list[NDArray[np.float64]],
    *,
    diameter_mm: float,
    method: str = "bundle",
    report_dir: str | os.PathLike[str] | None = None,
    progress: ProgressCallback | None = None,
    detect_s: float = 0.0,
    linked: NDArray[np.float64] | None = None,
    **options: Any,
) -> CalibrationResult:
    """Calibrate a scan from BB candidates already detected in its projections (one array per projection, in
    order; as :mod:`calib.live` collects them while the scan runs) and write the results in place, exactly
    as :func:`calibrate_scan` does. ``linked``: the candidates' 2-D tracks, linked frame by frame as
    :func:`calib.track.link_fragments` does with the options' ``jitter_mm`` (live calibration has them)."""
    with threadpool_limits(limits=1, user_api="blas"), CompileClock() as clock:
        opt = checked_options(method, options)
        target = Path(path)
        t0 = time.perf_counter()
        with ScanFile(target) as sf:
            inputs = _read_inputs(sf, target, check_frames=False)
            if len(candidates) != inputs.proj.size:
                raise OptionError(f"{target}: {len(candidates)} candidate lists for {inputs.proj.size} projections")
            d_px = projected_diameter_px(inputs.nominal, diameter_mm)
        return _solve_and_write(
            inputs, candidates, diameter_mm, d_px, method, opt, progress, clock, t0, detect_s, report_dir, linked
        )


def _calibrate_scan(
    path: str | os.PathLike[str],
    method: str,
    out: str | os.PathLike[str] | None,
    report_dir: str | os.PathLike[str] | None,
    progress: ProgressCallback | None,
    options: dict[str, Any],
    clock: CompileClock,
    seeds_uv: Any = None,
    workers: int = 2,
) -> CalibrationResult:
    opt = checked_options(method, options)
    src = Path(path)
    target = src
    if out is not None:
        target = Path(out)
        if target.resolve() != src.resolve():
            ScanFile(src).close()  # validate before writing anything
            write_linked_scan(src, target)  # reads the scan's frames from it: nothing copied, the scan unchanged
    t0 = time.perf_counter()
    with ScanFile(target) as sf:
        inputs = _read_inputs(sf, target)
        cands, diameter_mm, d_px = _detect(sf, inputs.proj, inputs.nominal, opt, progress, clock, seeds_uv, workers)
    t_detect = time.perf_counter() - t0 - clock.seconds  # kernels compiled on first use: not calibration time
    return _solve_and_write(inputs, cands, diameter_mm, d_px, method, opt, progress, clock, t0, t_detect, report_dir)


def _solve_and_write(
    inputs: _ScanInputs,
    cands: list[NDArray[np.float64]],
    diameter_mm: float,
    d_px: float,
    method: str,
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    clock: CompileClock,
    t0: float,
    t_detect: float,
    report_dir: str | os.PathLike[str] | None,
    linked: NDArray[np.float64] | None = None,
) -> CalibrationResult:
    """Identify the BBs in the candidates, estimate, judge, write ``/geometry/calibrated``; the result."""
    target, proj, nominal_all, truth_all = inputs.target, inputs.proj, inputs.nominal_all, inputs.truth_all
    n_all = nominal_all.n_views
    nominal = inputs.nominal
    min_obs = min_observations(opt, len(proj))
    model = ViewModel(nominal, opt.intrinsics)
    t1, compiled_before = time.perf_counter(), clock.seconds
    best: tuple[Any, ...] | None = None
    failure: NoMarkersError | None = None
    t_identify = 0.0
    # recovery: when the BBs cannot be followed with the orbit's expected jitter, or the views they give
    # fail the quality check, track again allowing larger frame-to-frame jumps; a result found that way is
    # kept only if it passes the check (a larger allowance also links more wrong blobs)
    levels = [opt.jitter_mm] + ([j for j in RECOVERY_JITTER_MM if j > opt.jitter_mm] if opt.recover else [])
    tracks: dict[float, tuple[TrackingSettings, NDArray[np.float64]]] = {}  # per allowance: settings, 2-D tracks
    for jitter_mm in levels:
        if jitter_mm in LAST_RESORT_JITTER_MM and best is not None:  # only where smaller ones found no BBs
            break
        report(progress, "track", 0, 1, f"identifying BBs (jitter {jitter_mm:g} mm)")
        tset = TrackingSettings(
            diameter_px=d_px, motion_px=motion_px(nominal), jitter_px=jitter_mm * d_px / diameter_mm
        )
        t_id, compiled_at_id = time.perf_counter(), clock.seconds
        frags = linked if linked is not None and jitter_mm == opt.jitter_mm else link_fragments(cands, tset, nominal)
        tracks[jitter_mm] = (tset, frags)
        uv, found_warnings = identify(
            cands,
            ViewModel(nominal, "fixed"),
            tset,
            diameter_mm,
            min_obs,
            prior_scale=max(1.0, jitter_mm / DEFAULT_JITTER_MM),
            linked=frags,
        )
        t_identify += time.perf_counter() - t_id - (clock.seconds - compiled_at_id)  # compiling counted once
        report(progress, "track", 1, 1, f"{uv.shape[1]} BBs")
        if uv.shape[1] < 3:
            failure = NoMarkersError(
                f"{target}: found {uv.shape[1]} BB(s) seen in at least {min_obs} frames; at least 3 are needed. "
                f"Either the BBs could not be followed from frame to frame (motion errors far beyond the nominal "
                f"orbit, even allowing {jitter_mm:g} mm jumps: check the nominal geometry), or they are not "
                f"{diameter_mm:.2f} mm ({d_px:.1f} px) BBs (give the size: orbitct calibrate --diameter-mm, or "
                '"diameter_mm" in POST /calibrations)'
            )
            continue
        try:
            outcome = estimate(method, model, uv, opt, progress)
        except NoMarkersError as exc:
            failure = exc
            continue
        verdict = judge(outcome[7], proj, opt.max_predicted_px, opt.bridge_max_views, method)
        if method == "bundle" and (not verdict.passed or verdict.counts[OWN] < proj.size):
            # views between calibrated ones may have jumped far: search as widely as REASSIGN_JITTER_MM at least
            wide = replace(tset, jitter_px=max(REASSIGN_JITTER_MM, jitter_mm) * d_px / diameter_mm)
            outcome, verdict = reassign(cands, model, wide, outcome, verdict, proj, opt, progress)
        if best is None or verdict.passed:  # a larger allowance replaces the first result only when it passes
            best = (jitter_mm, found_warnings, outcome, verdict)
        if verdict.passed or mild_misfits_only(outcome[7], verdict):
            break
    if best is None:
        assert failure is not None
        raise failure
    jitter_used, warnings, outcome, verdict = best
    n_split = 0
    if method == "bundle":
        tset, frags = tracks[jitter_used]
        outcome, verdict, n_found = recover_missed_bbs(
            cands, model, tset, outcome, verdict, proj, diameter_mm, min_obs, opt, progress, frags
        )
        if n_found:
            warnings = list(warnings) + [
                f"{n_found} BB(s) lost while identifying (their tracks broke into short pieces) "
                "were found again through the calibrated views and calibrated with the rest"
            ]
        outcome, verdict, n_twins = merge_twins(model, outcome, verdict, proj, opt, progress)
        if n_twins:
            warnings = list(warnings) + [
                f"{n_twins} BBs were identified twice, in two parts of the orbit (tracking broke "
                "for every BB at once); each pair was made one BB and calibrated again"
            ]
            # BBs identified in one part only: the other part's views find them through the merged geometry
            outcome, verdict = reassign(cands, model, tset, outcome, verdict, proj, opt, progress, must_improve=False)
        outcome, verdict, n_sparse = sparse_views_again(
            cands, model, tracks[opt.jitter_mm][0], outcome, verdict, proj, opt, progress
        )
        if n_sparse:
            warnings = list(warnings) + [
                f"{n_sparse} view(s) that kept {MIN_OWN_BBS} BBs or fewer where the views around "
                "them see more were assigned again through those views and calibrated with more BBs"
            ]
        n_jumped = 0
        # only where the BBs were followed only with jumps larger than reassignment searches: elsewhere a view
        # without its own BBs lacks them for other reasons, and a 2-D placing can pick a wrong blob. Each round's
        # views are the next round's neighbours
        for _ in range(JUMPED_ROUNDS if jitter_used > REASSIGN_JITTER_MM else 0):
            outcome, verdict, gained = jumped_views_again(
                cands, model, tracks[jitter_used][0], outcome, verdict, proj, opt, progress
            )
            n_jumped += gained
            if not gained:
                break
        if n_jumped:
            warnings = list(warnings) + [
                f"{n_jumped} view(s) whose frame jumped farther than the BBs lie apart were placed by the 2-D "
                "similarity that carries the most BBs onto blobs and calibrated from their own BBs"
            ]
        outcome, verdict, n_split = split_merged(target, proj, model, outcome, verdict, d_px, opt, progress)
        if opt.weigh_detections:
            # identification and its checks weigh every detection alike (a wrong blob over a bone edge must keep
            # its pull to be found); the detections they kept are then solved once more, each weighted by how
            # rough its background is, and that solution replaces the first unless it judges worse
            outcome, verdict, _ = estimate_again(
                model,
                outcome[3],
                proj,
                opt,
                progress,
                outcome,
                verdict,
                polish=Polish(outcome, partial(detection_spread, cands)),
            )
    geometry_p, xyz, state, uv, history, n_iter, more, quality = outcome
    warnings = list(warnings) + more
    bar = None
    if opt.scale_bar_mm is not None:
        bar = find_scale_bar(xyz, opt.scale_bar_mm, opt.scale_bar_bbs)
        geometry_p, xyz = rescaled_views(geometry_p, bar.factor), xyz * bar.factor
        state = ViewState(state.R, state.t + (bar.factor - 1.0) * geometry_p.S / bar.factor, state.k)
        history = [(rpe * bar.factor, resid) for rpe, resid in history]  # RPE is a distance: it scales, pixels do not
    if jitter_used != opt.jitter_mm:
        warnings.append(
            f"the BBs were followed only when allowing {jitter_used:g} mm jumps between frames (the "
            f"orbit's expected jitter is {opt.jitter_mm:g} mm, option jitter_mm): the orbit is far "
            "from its nominal"
        )
    t_est = time.perf_counter() - t1 - (clock.seconds - compiled_before) - t_identify  # identification apart
    solved = geometry_p.valid
    unsolved = proj[~solved]
    warnings += verdict.warnings
    warnings[:0] = inputs.file_warnings
    resid = residual_px(geometry_p, uv, xyz)
    ok_r = np.isfinite(resid)
    reproj_rms = float(np.sqrt(np.mean(resid[ok_r] ** 2))) if ok_r.any() else float("nan")
    stats = [iteration_stats(i, rpe, r) for i, (rpe, r) in enumerate(history)]
    full_vec = np.full((n_all, 12), np.nan)
    full_vec[proj] = geometry_p.vectors
    full_geom = nominal_all.with_vectors(full_vec)
    uv_all = np.full((n_all, uv.shape[1], 2), np.nan)
    uv_all[proj] = uv
    rpe_all = np.full(n_all, np.nan)
    rpe_all[proj] = np.where(quality.status == "own", rpe_per_frame(geometry_p, uv, xyz), np.nan)
    status_all = np.full(n_all, -1, np.int8)
    status_all[proj] = [STATUS_CODES[str(v)] for v in quality.status]
    predicted_all = np.full(n_all, np.nan)
    predicted_all[proj] = quality.predicted_px
    elapsed = time.perf_counter() - t0 - clock.seconds
    t_check = elapsed - t_detect - t_identify - t_est  # the rest: quality check and per-view figures
    t_write = time.perf_counter()
    report(progress, "write", 0, 1, str(target))
    with ScanFile(target, "r+") as sf:
        sf.write_calibration(
            full_geom,
            uv=uv_all,
            xyz=xyz,
            rpe_mm=rpe_all,
            method=method,
            iterations=n_iter,
            elapsed_s=elapsed,
            reproj_rms_px=reproj_rms,
            extra_attrs={
                "n_bbs": int(xyz.shape[0]),
                "bb_diameter_mm": float(diameter_mm),
                "intrinsics": opt.intrinsics,
                "gauge": (
                    bar.describe()
                    if bar is not None
                    else "BB constellation keeps centroid, orientation and RMS size of its nominal triangulation"
                    if method == "bundle"
                    else "none (paper method)"
                ),
                **(
                    {}
                    if bar is None
                    else {
                        "scale_bar_mm": bar.length_mm,
                        "scale_bar_bbs": [b + 1 for b in bar.bbs],
                        "scale_factor": bar.factor,
                    }
                ),
                "warnings_json": list(warnings),
                "split_blobs": n_split,
                **verdict.attrs(),
            },
            per_view={"view_status": status_all, "predicted_px": predicted_all},
        )
    report(progress, "write", 1, 1, str(target))
    t_write = time.perf_counter() - t_write
    corr_R = np.full((n_all, 3), np.nan)
    corr_t = np.full((n_all, 3), np.nan)
    corr_R[proj] = np.where(solved[:, None], state.rotvec, np.nan)
    corr_t[proj] = np.where(solved[:, None], state.t, np.nan)
    result = CalibrationResult(
        method=method,
        path=target,
        geometry=full_geom,
        nominal=nominal_all,
        uv=uv_all,
        xyz=xyz,
        rpe_mm=rpe_all,
        n_frames=int(proj.size),
        iterations=stats,
        rpe_history=[h[0] for h in history],
        elapsed_s=elapsed,
        detect_s=t_detect,
        estimate_s=t_est,
        compile_s=clock.seconds,
        identify_s=t_identify,
        check_s=t_check,
        write_s=t_write,
        reproj_rms_px=reproj_rms,
        corrections={"rotvec_rad": corr_R, "shift_mm": corr_t, "frame": np.arange(n_all)},
        warnings=warnings,
        unsolved_views=unsolved.tolist(),
        true_corrections=None if truth_all is None else true_corrections(full_geom, nominal_all, truth_all),
        quality=verdict,
        view_status=status_all,
        predicted_px=predicted_all,
        scale_bar=bar,
    )
    if report_dir is not None:
        from calib.report import write_report

        write_report(result, Path(report_dir))
    return result


__all__ = [
    "METHODS",
    "CalibrationOptions",
    "CalibrationResult",
    "IterationStats",
    "calibrate_candidates",
    "calibrate_scan",
    "projected_diameter_px",
]
