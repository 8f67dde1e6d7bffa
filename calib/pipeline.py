"""``calibrate_scan``: detect BBs in a scan file, identify them, estimate the geometry, write the results."""

from __future__ import annotations

import os
import shutil
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, fields, replace
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from calib.bundle import bundle_adjust
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
from calib.identify import assign_by_pose, fill_states, identify, recover_missed, twin_constellation, usable_views
from calib.model import INTRINSICS, ViewModel, ViewState
from calib.paper import paper_calibrate
from calib.quality import (
    FAILED,
    FIRST_LOSS_SCALE_PX,
    MIN_OWN_BBS,
    OWN,
    STATUS_CODES,
    Verdict,
    ViewQuality,
    assess_views,
    centroid_noise_px,
    fit_rigid_poses,
    huber_threshold_px,
    judge,
    misfit_limit_px,
    view_misfit_px,
)
from calib.rays import marker_rays, rpe_per_frame, triangulate_least_squares
from calib.scale import ScaleBar, find_scale_bar, rescaled_views
from calib.split import FrameWindows, SplitSettings, fit_pair, isolated, merged_pairs, radial_profile
from calib.track import TrackingSettings, link_fragments
from orbitct.compiletime import CompileClock
from orbitct.geometry import ViewGeometry
from orbitct.progress import ProgressCallback, report
from orbitct.scanfile import ImageKey, ScanFile, describe_frame_problems, frame_problem
from orbitct.scanfile.reader import FRAME_COPIES
from orbitct.statistics import rpe_statistics

METHODS = ("bundle", "paper")
SPLIT_MIN_SHARE = 0.01  # blobs of two BBs are split when there are at least this share of the detections
DEFAULT_JITTER_MM = 3.0
RECOVERY_JITTER_MM = (8.0, 15.0, 25.0)  # tracking allowances tried in turn when the BBs are not followed


@dataclass
class CalibrationOptions:
    """Tunable settings of :func:`calibrate_scan` (pass as keyword options)."""

    iterations: int | None = None  # paper: alternations (default 3); bundle: max LM iterations (default 30)
    intrinsics: str = "fixed"  # bundle only: "fixed", "sdd" or "sdd+pp"
    loss_scale_px: float | None = None  # Huber threshold (px); default: 1.5 x the measured centroid noise
    min_bbs_per_view: int = 3  # a view with fewer is never fitted on its own (the bundle needs 4 to call it its own)
    bridge_max_views: int = 10  # bundle: widest run of views without 4 BBs that is bridged from its neighbours
    max_predicted_px: float = 0.5  # quality check: largest predicted field-of-view error a view may have
    min_observations: int | None = None  # frames a BB must be seen in (default max(8, 5% of projections))
    diameter_mm: float | None = None  # BB diameter; default /markers@diameter_mm, else estimated
    k_sigma: float = 6.0  # detection threshold in noise standard deviations
    max_candidates: int = 128  # strongest peaks kept per frame, at least (see calib.detect.CANDIDATE_AREA_PX)
    outlier_px: float = 1.0  # bundle: detections off by more than max(this, 6 robust sigma) become NaN
    workers: int = 2  # detection threads
    seeds_uv: Any = None  # optional (K, 2) BB positions (col, row) in the first projection
    jitter_mm: float = (
        DEFAULT_JITTER_MM  # frame-to-frame jitter of the orbit around the nominal (object scale) for tracking
    )
    recover: bool = True  # track again allowing larger jumps (RECOVERY_JITTER_MM) when the first result fails
    scale_bar_mm: float | None = None  # known distance between two BBs (a scale bar): sets the metric scale
    scale_bar_bbs: tuple[int, int] | None = (
        None  # which BBs span it (1-based, as the report numbers them); default: the one pair near its length
    )
    weigh_detections: bool = (
        True  # bundle: solve once more at the end, each detection weighted by how rough its background is
    )


@dataclass
class IterationStats:
    """RPE summary of one iteration (index 0 = the initial geometry)."""

    index: int
    rpe_mean_mm: float
    rpe_median_mm: float
    rpe_std_mm: float
    reproj_rms_px: float


@dataclass
class CalibrationResult:
    """What a calibration found and where it was written."""

    method: str
    path: Path
    geometry: ViewGeometry
    nominal: ViewGeometry
    uv: NDArray[np.float64]
    xyz: NDArray[np.float64]
    rpe_mm: NDArray[np.float64]
    n_frames: int
    iterations: list[IterationStats]
    rpe_history: list[NDArray[np.float64]]
    elapsed_s: float
    detect_s: float
    estimate_s: float
    reproj_rms_px: float
    corrections: dict[str, NDArray[np.float64]]
    warnings: list[str] = field(default_factory=list)
    unsolved_views: list[int] = field(default_factory=list)
    true_corrections: dict[str, NDArray[np.float64]] | None = None  # simulated scans: the truth, same frame
    quality: Verdict | None = None
    compile_s: float = 0.0  # numba compiling its kernels on first use (after installation); not in elapsed_s
    view_status: NDArray[np.int8] | None = None  # per frame: STATUS_CODES, -1 for non-projections
    predicted_px: NDArray[np.float64] | None = None  # per frame: predicted field-of-view error (px)
    scale_bar: ScaleBar | None = None  # the pair of BBs that set the metric scale, when a scale bar was given

    @property
    def n_bbs(self) -> int:
        """Number of BBs found."""
        return int(self.xyz.shape[0])

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary (no per-frame arrays)."""
        last = self.iterations[-1]
        return {
            "method": self.method,
            "path": str(self.path),
            "n_frames": self.n_frames,
            "n_bbs": self.n_bbs,
            "elapsed_s": self.elapsed_s,
            "detect_s": self.detect_s,
            "estimate_s": self.estimate_s,
            "compile_s": self.compile_s,
            "rpe_mean_mm": last.rpe_mean_mm,
            "rpe_median_mm": last.rpe_median_mm,
            "rpe_std_mm": last.rpe_std_mm,
            "reproj_rms_px": self.reproj_rms_px,
            "iterations": [asdict(s) for s in self.iterations],
            "warnings": list(self.warnings),
            "unsolved_views": list(self.unsolved_views),
            "quality": self.quality.summary() if self.quality is not None else None,
            "scale": self.scale_line(),
        }

    def scale_line(self) -> str:
        """Where the metric scale comes from, in words."""
        if self.scale_bar is not None:
            return self.scale_bar.describe()
        if self.method != "bundle":
            return "metric scale from the nominal geometry (the paper method fixes no gauge)"
        return (
            "metric scale from the nominal geometry: distances in the calibrated frame can be off by about the "
            "orbit's mean error along the beam over the source distance (1-2 % on the bench profile); a scale bar "
            "fixes it (--scale-bar-mm)"
        )


def _options(method: str, options: dict[str, Any]) -> CalibrationOptions:
    if method not in METHODS:
        raise OptionError(f"method must be one of {METHODS}, got {method!r}")
    known = {f.name for f in fields(CalibrationOptions)}
    unknown = set(options) - known
    if unknown:
        raise OptionError(f"unknown option(s) {sorted(unknown)}; allowed are {sorted(known)}")
    opt = CalibrationOptions(**options)
    if opt.intrinsics not in INTRINSICS:
        raise OptionError(f"intrinsics must be one of {sorted(INTRINSICS)}, got {opt.intrinsics!r}")
    if method == "paper" and opt.intrinsics != "fixed":
        raise OptionError("the paper method estimates rigid poses only; use intrinsics='fixed'")
    if opt.min_bbs_per_view < 3:
        raise OptionError(f"min_bbs_per_view must be >= 3 (a rigid pose needs 3 BBs), got {opt.min_bbs_per_view}")
    if opt.diameter_mm is not None and not opt.diameter_mm > 0:
        raise OptionError(f"diameter_mm must be > 0, got {opt.diameter_mm}")
    if opt.scale_bar_mm is not None and not (np.isfinite(opt.scale_bar_mm) and opt.scale_bar_mm > 0):
        raise OptionError(f"scale_bar_mm must be a positive length in mm, got {opt.scale_bar_mm}")
    if opt.scale_bar_bbs is not None and opt.scale_bar_mm is None:
        raise OptionError("scale_bar_bbs names the BBs of a scale bar: give its length too (scale_bar_mm)")
    return opt


def _stats(index: int, rpe: NDArray[np.float64], resid_px: NDArray[np.float64]) -> IterationStats:
    st = rpe_statistics(rpe)
    r = resid_px[np.isfinite(resid_px)]
    return IterationStats(
        index, st.mean_mm, st.median_mm, st.std_mm, float(np.sqrt(np.mean(r**2))) if r.size else float("nan")
    )


def _motion_px(nominal: ViewGeometry) -> float:
    """95th percentile of how far points in the field of view move between neighbouring projections (px)."""
    if nominal.n_views < 2:
        return 0.0
    uv = nominal.project(fov_points(nominal, 4))
    step = np.linalg.norm(np.diff(uv, axis=0), axis=-1)
    return float(np.nanpercentile(step, 95))


def _residual_px(geometry: ViewGeometry, uv: NDArray[np.float64], xyz: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.linalg.norm(geometry.project(xyz) - uv, axis=-1)


def _detect(
    sf: ScanFile,
    proj: NDArray[np.intp],
    nominal: ViewGeometry,
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
) -> tuple[list[NDArray[np.float64]], float, float]:
    """Candidates of every projection, streamed frame by frame; also BB diameter (mm and px)."""
    det = sf.panel
    mag = float(np.median(nominal.sdd / nominal.sod()))
    pitch = float(np.sqrt(det.pitch_col * det.pitch_row))
    dark, flat = sf.dark_flat()
    ds = sf.frames
    diameter_mm = opt.diameter_mm if opt.diameter_mm is not None else sf.marker_diameter_mm
    if diameter_mm is None:
        diameter_mm = _estimate_diameter_mm(sf, proj, dark, flat, mag, pitch, opt)
    d_px = projected_diameter_px(nominal, diameter_mm)
    fd = frame_detector(dark, flat, d_px, opt)
    total = len(proj)
    step = max(1, total // 100)
    cands: list[NDArray[np.float64]] = [np.zeros((0, N_FIELDS))] * total
    problems: dict[int, str] = {}

    def checked(buf: NDArray[Any]) -> NDArray[np.float64]:  # a frame that cannot be used yields no candidates
        why = frame_problem(buf, projection=True)
        return fd.candidates(buf) if why is None else np.array([why], dtype=object)

    def take(m: int, c: NDArray[Any]) -> None:
        if c.dtype == object:
            problems[int(proj[m])] = str(c[0])
            c = np.zeros((0, N_FIELDS))
        cands[m] = c

    # the main thread reads frames (h5py holds the GIL); workers run the GIL-free kernels
    with ThreadPoolExecutor(max_workers=max(1, opt.workers)) as pool:
        pending: deque[tuple[int, Future[NDArray[Any]]]] = deque()
        for n, i in enumerate(proj):
            buf = np.empty(det.shape, dtype=ds.dtype)
            ds.read_direct(buf, np.s_[int(i)])
            if n == 0:
                c = checked(buf)  # also fixes the noise level used for every frame
                if opt.seeds_uv is not None and c.dtype != object:
                    c = np.concatenate([_seed_records(buf, fd, np.asarray(opt.seeds_uv, float)), c])
                take(0, c)
                continue
            pending.append((n, pool.submit(checked, buf)))
            while len(pending) > 2 * max(1, opt.workers) or (pending and pending[0][1].done()):
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
    report(progress, "detect", total, total, "")
    return cands, float(diameter_mm), d_px


def frame_detector(
    dark: NDArray[np.float32], flat: NDArray[np.float32], d_px: float, opt: CalibrationOptions
) -> FrameDetector:
    """The detector every projection of a scan goes through (BB size in pixels, the options' threshold)."""
    settings = settings_for(d_px, dark.shape)
    settings.k_sigma, settings.max_candidates = opt.k_sigma, opt.max_candidates
    return FrameDetector(dark, flat, settings)


def _seed_records(raw: NDArray[Any], fd: FrameDetector, seeds: NDArray[np.float64]) -> NDArray[np.float64]:
    if seeds.ndim != 2 or seeds.shape[1] != 2:
        raise OptionError(f"seeds_uv must have shape (K, 2) as (col, row), got {seeds.shape}")
    out = []
    r = 0.5 * fd.settings.diameter_px
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
    **options: Any,
) -> CalibrationResult:
    """Calibrate a scan's geometry from the BBs in its projections and write the results."""
    # the linear algebra here is small; BLAS threads would only spin against the detection threads
    with threadpool_limits(limits=1, user_api="blas"), CompileClock() as clock:
        return _calibrate_scan(path, method, out, report_dir, progress, options, clock)


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
        opt = _options(method, options)
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
) -> CalibrationResult:
    opt = _options(method, options)
    src = Path(path)
    target = src
    if out is not None:
        target = Path(out)
        if target.resolve() != src.resolve():
            ScanFile(src).close()  # validate before copying
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, target)
    t0 = time.perf_counter()  # the copy above is not part of the calibration time
    with ScanFile(target) as sf:
        inputs = _read_inputs(sf, target)
        cands, diameter_mm, d_px = _detect(sf, inputs.proj, inputs.nominal, opt, progress)
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
    min_obs = _min_observations(opt, len(proj))
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
        report(progress, "track", 0, 1, f"identifying BBs (jitter {jitter_mm:g} mm)")
        tset = TrackingSettings(
            diameter_px=d_px, motion_px=_motion_px(nominal), jitter_px=jitter_mm * d_px / diameter_mm
        )
        t_id = time.perf_counter()
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
        t_identify += time.perf_counter() - t_id
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
            outcome = _estimate(method, model, uv, opt, progress)
        except NoMarkersError as exc:
            failure = exc
            continue
        verdict = judge(outcome[7], proj, opt.max_predicted_px, opt.bridge_max_views, method)
        if method == "bundle" and (not verdict.passed or verdict.counts[OWN] < proj.size):
            # views between calibrated ones may have jumped far: search as widely as the widest allowance
            wide = replace(tset, jitter_px=max(levels) * d_px / diameter_mm)
            outcome, verdict = _reassign(cands, model, wide, outcome, verdict, proj, opt, progress)
        if best is None or verdict.passed:  # a larger allowance replaces the first result only when it passes
            best = (jitter_mm, found_warnings, outcome, verdict)
        if verdict.passed or _mild_misfits_only(outcome[7], verdict):
            break
    if best is None:
        assert failure is not None
        raise failure
    jitter_used, warnings, outcome, verdict = best
    n_split = 0
    if method == "bundle":
        tset, frags = tracks[jitter_used]
        outcome, verdict, n_found = _recover_missed(
            cands, model, tset, outcome, verdict, proj, diameter_mm, min_obs, opt, progress, frags
        )
        if n_found:
            warnings = list(warnings) + [
                f"{n_found} BB(s) lost while identifying (their tracks broke into short pieces) "
                "were found again through the calibrated views and calibrated with the rest"
            ]
        outcome, verdict, n_twins = _merge_twins(model, outcome, verdict, proj, opt, progress)
        if n_twins:
            warnings = list(warnings) + [
                f"{n_twins} BBs were identified twice, in two parts of the orbit (tracking broke "
                "for every BB at once); each pair was made one BB and calibrated again"
            ]
            # BBs identified in one part only: the other part's views find them through the merged geometry
            outcome, verdict = _reassign(cands, model, tset, outcome, verdict, proj, opt, progress, must_improve=False)
        outcome, verdict, n_sparse = _sparse_views_again(
            cands, model, tracks[opt.jitter_mm][0], outcome, verdict, proj, opt, progress
        )
        if n_sparse:
            warnings = list(warnings) + [
                f"{n_sparse} view(s) that kept {MIN_OWN_BBS} BBs or fewer where the views around "
                "them see more were assigned again through those views and calibrated with more BBs"
            ]
        outcome, verdict, n_split = _split_merged(target, proj, model, outcome, verdict, d_px, opt, progress)
        if opt.weigh_detections:
            # identification and its checks weigh every detection alike (a wrong blob over a bone edge must keep
            # its pull to be found); the detections they kept are then solved once more, each weighted by how
            # rough its background is, and that solution replaces the first unless it judges worse
            outcome, verdict, _ = _estimate_again(
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
    resid = _residual_px(geometry_p, uv, xyz)
    ok_r = np.isfinite(resid)
    reproj_rms = float(np.sqrt(np.mean(resid[ok_r] ** 2))) if ok_r.any() else float("nan")
    stats = [_stats(i, rpe, r) for i, (rpe, r) in enumerate(history)]
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


def _reassign(
    cands: list[NDArray[np.float64]],
    model: ViewModel,
    tset: TrackingSettings,
    outcome: tuple[Any, ...],
    verdict: Verdict,
    proj: NDArray[np.intp],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    *,
    must_improve: bool = True,
) -> tuple[tuple[Any, ...], Verdict]:
    """Assign the detections again, to every BB predicted through the calibrated geometry (views not calibrated
    from their own BBs: through their nearest view that is), and estimate again; kept when it passes where the
    first did not, or calibrates more views from their own BBs (not ``must_improve``: unless it fails where the
    first passed or calibrates fewer views from their own BBs). Tracking predicts through rough poses, which
    miss BBs in views that see few of them (a truncating panel) or jump far (a robotic arm)."""
    xyz, state, uv = outcome[1], outcome[2], outcome[3]
    solved = outcome[7].status == OWN
    if not solved.any():
        return outcome, verdict
    filled = fill_states(ViewState(np.nan_to_num(state.R), np.nan_to_num(state.t), state.k), solved, len(solved))
    again = assign_by_pose(cands, model, filled, xyz, tset)
    if np.array_equal(again, uv, equal_nan=True):
        return outcome, verdict
    outcome, verdict, _ = _estimate_again(
        model, again, proj, opt, progress, outcome, verdict, must_improve=must_improve
    )
    return outcome, verdict


def _estimate_again(
    model: ViewModel,
    uv: NDArray[np.float64],
    proj: NDArray[np.intp],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    outcome: tuple[Any, ...],
    verdict: Verdict,
    *,
    must_improve: bool = False,
    polish: Polish | None = None,
) -> tuple[tuple[Any, ...], Verdict, bool]:
    """Estimate again from detections ``uv`` (or, with ``polish``, solve once more from a previous outcome):
    that outcome and verdict (and True) unless it fails where the first passed or calibrates fewer views from their
    own BBs (or, ``must_improve``, does no better on both)."""
    try:
        second = _estimate("bundle", model, uv, opt, progress, polish)
    except NoMarkersError:
        return outcome, verdict, False
    second_verdict = judge(second[7], proj, opt.max_predicted_px, opt.bridge_max_views, "bundle")
    new, old = (second_verdict.passed, second_verdict.counts["own"]), (verdict.passed, verdict.counts["own"])
    if new > old or (new == old and not must_improve):
        return second, second_verdict, True
    return outcome, verdict, False


def _recover_missed(
    cands: list[NDArray[np.float64]],
    model: ViewModel,
    tset: TrackingSettings,
    outcome: tuple[Any, ...],
    verdict: Verdict,
    proj: NDArray[np.intp],
    diameter_mm: float,
    min_obs: int,
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    frags: NDArray[np.float64],
) -> tuple[tuple[Any, ...], Verdict, int]:
    """Look for BBs that identification lost (:func:`calib.identify.recover_missed`) among the 2-D tracks ``frags``
    it was given, through the calibrated views; with any found, assign and estimate again with them; kept unless it
    fails where the first passed or calibrates fewer views from their own BBs. Also the number found."""
    geometry, xyz, state = outcome[0], outcome[1], outcome[2]
    solved = outcome[7].status == OWN
    if not solved.any():
        return outcome, verdict, 0
    missed = recover_missed(cands, geometry, xyz, frags, tset, min_obs, diameter_mm)
    if not len(missed):
        return outcome, verdict, 0
    filled = fill_states(ViewState(np.nan_to_num(state.R), np.nan_to_num(state.t), state.k), solved, len(solved))
    again = assign_by_pose(cands, model, filled, np.concatenate([xyz, missed]), tset)
    outcome, verdict, kept = _estimate_again(model, again, proj, opt, progress, outcome, verdict)
    return outcome, verdict, len(missed) if kept else 0


def _merge_twins(
    model: ViewModel,
    outcome: tuple[Any, ...],
    verdict: Verdict,
    proj: NDArray[np.intp],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
) -> tuple[tuple[Any, ...], Verdict, int]:
    """BBs identified twice, once in each of two parts of the orbit that nothing else ties together
    (:func:`calib.identify.twin_constellation`; experiment C at 512 px: every track broke at one frame, and the
    second half calibrated as a constellation of its own, 8-22 px off, and passed). Each pair is made one BB (the
    detections of both; in a frame that saw both, neither) and the geometry estimated again. That result replaces
    the split one whatever its verdict; where it cannot be estimated, the split one stands, failed. Also how many
    pairs were merged."""
    xyz, uv = outcome[1], outcome[3]
    pairs = twin_constellation(xyz, uv)
    if not pairs:
        return outcome, verdict, 0
    merged = uv.copy()
    for a, b in pairs:
        has_a, has_b = np.isfinite(merged[:, a]).all(-1), np.isfinite(merged[:, b]).all(-1)
        merged[~has_a & has_b, a] = merged[~has_a & has_b, b]
        merged[has_a & has_b, a] = np.nan
    merged = np.delete(merged, [b for _, b in pairs], axis=1)
    try:
        again = _estimate("bundle", model, merged, opt, progress)
    except NoMarkersError:
        reason = (
            f"{len(pairs)} BBs were identified twice, in two parts of the orbit that nothing ties together "
            "(tracking broke for every BB at once): those parts' geometries can be far apart"
        )
        return outcome, replace(verdict, passed=False, reasons=[*verdict.reasons, reason]), 0
    return again, judge(again[7], proj, opt.max_predicted_px, opt.bridge_max_views, "bundle"), len(pairs)


#: views either side that :func:`_sparse_views_again` compares a view's BB count with
_AROUND = 3


def _sparse_views_again(
    cands: list[NDArray[np.float64]],
    model: ViewModel,
    tset: TrackingSettings,
    outcome: tuple[Any, ...],
    verdict: Verdict,
    proj: NDArray[np.intp],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
) -> tuple[tuple[Any, ...], Verdict, int]:
    """Views left with :data:`MIN_OWN_BBS` BBs or fewer where the views around them (three either side) see at
    least two more: frames that jumped, where tracking kept few blobs, perhaps wrong ones that a pose with two
    measurements to spare absorbs (experiment C at 512 px: two of four blobs wrong, views 5.8 and 7 px off and
    passing, a bridged neighbour with them). Their BBs are assigned again through the poses of the views around
    them (``tset``: the orbit's own jitter) and the geometry estimated again with the views that gain BBs; kept
    unless worse. Also how many views gained."""
    state, uv, quality = outcome[2], outcome[3], outcome[7]
    count = np.isfinite(uv).all(-1).sum(1)
    if count.size < 3:
        return outcome, verdict, 0
    padded = np.pad(count.astype(float), _AROUND, constant_values=np.nan)
    window = np.lib.stride_tricks.sliding_window_view(padded, 2 * _AROUND + 1)
    around = np.nanmedian(np.delete(window, _AROUND, axis=1), axis=1)
    sparse = (count <= MIN_OWN_BBS) & (around >= count + 2)
    if not sparse.any():
        return outcome, verdict, 0
    solved = (quality.status == OWN) & ~sparse
    filled = fill_states(ViewState(np.nan_to_num(state.R), np.nan_to_num(state.t), state.k), solved, len(solved))
    again = assign_by_pose(cands, model, filled, outcome[1], tset)
    gain = sparse & (np.isfinite(again).all(-1).sum(1) > count)
    if not gain.any():
        return outcome, verdict, 0
    new = uv.copy()
    new[gain] = again[gain]
    outcome, verdict, kept = _estimate_again(model, new, proj, opt, progress, outcome, verdict)
    return outcome, verdict, int(gain.sum()) if kept else 0


def _mild_misfits_only(quality: ViewQuality, verdict: Verdict) -> bool:
    """Whether the only reason a result failed is a few views with enough BBs whose residual exceeds the misfit
    limit by less than half again (centroid biases, not a BB taken for another, which leaves pixels): tracking
    again with larger jumps cannot change that, so the recovery stops (the verdict still fails)."""
    odd = quality.inconsistent
    if len(verdict.reasons) != 1 or not odd.any() or ((quality.status == FAILED) & ~odd).any():
        return False
    return float(np.nanmax(quality.misfit_px[odd])) < 1.5 * misfit_limit_px(quality.noise_px)


def _split_merged(
    target: Path,
    proj: NDArray[np.intp],
    model: ViewModel,
    outcome: tuple[Any, ...],
    verdict: Verdict,
    d_px: float,
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
) -> tuple[tuple[Any, ...], Verdict, int]:
    """Views where two BBs project onto one blob (both left out by the assignment): their two centroids fitted
    in the frame (:mod:`calib.split`), then the geometry estimated again; kept when the result is no worse.
    Also the number of blobs split. Only when such blobs are at least :data:`SPLIT_MIN_SHARE` of the detections:
    BBs that cross now and then change nothing measurable (experiment A at 768 px: 17 blobs among 4000
    detections, 0.129 px either way) but the fits and the second estimate would cost 0.3 s."""
    geometry_p, xyz, uv = outcome[0], outcome[1], outcome[3]
    with np.errstate(invalid="ignore"):
        predicted = geometry_p.project(xyz)
    s = SplitSettings(diameter_px=d_px, max_shift_px=max(2.0, 0.5 * d_px))
    pairs = merged_pairs(predicted, uv, TrackingSettings(diameter_px=d_px).overlap_factor * d_px)
    if len(pairs) < SPLIT_MIN_SHARE * np.isfinite(uv).all(-1).sum():
        return outcome, verdict, 0
    report(progress, "split", 0, len(pairs), "blobs of two BBs")
    new = uv.copy()
    n_split = 0
    with ScanFile(target) as sf:
        dark, flat = sf.dark_flat()
        den = np.maximum(flat - dark, 1.0).astype(np.float32)
        for p in sorted({v for v, _, _ in pairs}):
            frame = FrameWindows(np.asarray(sf.frames[int(proj[p])]), dark, den)
            profile = radial_profile(frame, uv[p, isolated(predicted[p], uv[p], 2.0 * d_px + 4.0)], s.radius_px)
            if profile is None:
                continue
            for _, j, k in (q for q in pairs if q[0] == p):
                guess = predicted[p, [j, k]]
                fit = fit_pair(frame, guess, profile, s)
                if fit is not None and fit.trusted(guess, s):
                    new[p, [j, k]] = fit.uv
                    n_split += 1
    report(progress, "split", len(pairs), len(pairs), f"{n_split} split")
    if n_split == 0:
        return outcome, verdict, 0
    outcome, verdict, kept = _estimate_again(model, new, proj, opt, progress, outcome, verdict)
    return outcome, verdict, n_split if kept else 0


def _leave_one_out_outliers(
    model: ViewModel, state: ViewState, xyz: NDArray[np.float64], uv: NDArray[np.float64], tol_px: float
) -> NDArray[np.bool_]:
    """Per view with 4 or more BBs, the detection whose residual, with the view's pose refitted without it,
    is largest and above ``tol_px``."""
    n, k = uv.shape[:2]
    seen = np.isfinite(uv).all(-1)
    views = np.flatnonzero(seen.sum(1) >= 5)  # with 4, the pose refitted on 3 has no redundancy to judge by
    out = np.zeros((n, k), bool)
    if views.size == 0:
        return out
    rep_v = np.repeat(views, k)
    rep_k = np.tile(np.arange(k), views.size)
    keep = seen[rep_v, rep_k]
    rep_v, rep_k = rep_v[keep], rep_k[keep]
    sub = ViewModel(model.nominal[rep_v], model.intrinsics)
    obs = uv[rep_v].copy()
    obs[np.arange(len(rep_v)), rep_k] = np.nan  # all left-out problems at once
    st = fit_rigid_poses(sub, ViewState(state.R[rep_v], state.t[rep_v], state.k[rep_v]), xyz, obs, iterations=4)
    pred = sub.project(st, xyz)
    loo = np.linalg.norm(pred[np.arange(len(rep_v)), rep_k] - uv[rep_v, rep_k], axis=-1)
    worst = np.full((n, k), -1.0)
    worst[rep_v, rep_k] = loo
    kmax = worst.argmax(1)
    flag = worst[np.arange(n), kmax] > tol_px
    out[np.flatnonzero(flag), kmax[flag]] = True
    return out


def _drop_single_misfits(
    model: ViewModel,
    state: ViewState,
    xyz: NDArray[np.float64],
    uv: NDArray[np.float64],
    quality: ViewQuality,
    min_own_bbs: int,
) -> tuple[ViewState, NDArray[np.float64], int]:
    """Views that failed only because one detection disagrees with the rest (a biased centroid, a BB taken for
    another): without that detection, and with the pose refitted to the others, they fit within the misfit limit
    and still see ``min_own_bbs`` BBs. Returns the states and detections with those views mended, and how many."""
    limit = misfit_limit_px(quality.noise_px)
    views = np.flatnonzero(quality.inconsistent & (quality.n_bbs >= max(min_own_bbs + 2, 6)))  # 5+ BBs stay
    if views.size == 0:
        return state, uv, 0
    sub = ViewModel(model.nominal[views], model.intrinsics)
    st = ViewState(state.R[views], state.t[views], state.k[views])
    worst = _leave_one_out_outliers(sub, st, xyz, uv[views], 0.0)
    trial = uv[views].copy()
    trial[worst] = np.nan
    refit = fit_rigid_poses(sub, st, xyz, trial, iterations=4)
    mended = np.nan_to_num(view_misfit_px(sub, refit, xyz, trial), nan=np.inf) <= limit
    if not mended.any():
        return state, uv, 0
    idx = views[mended]
    uv = uv.copy()
    uv[idx] = trial[mended]
    R, t, k = state.R.copy(), state.t.copy(), state.k.copy()
    R[idx], t[idx], k[idx] = refit.R[mended], refit.t[mended], refit.k[mended]
    return ViewState(R, t, k), uv, int(idx.size)


def _disagree_with_neighbour(
    model: ViewModel,
    state: ViewState,
    xyz: NDArray[np.float64],
    uv: NDArray[np.float64],
    tol_px: float,
    max_bbs: int = 3,
) -> NDArray[np.bool_]:
    """Detections in views seeing at most ``max_bbs`` BBs that lie more than ``tol_px`` from where the previous
    (or next) view's geometry puts them, after removing the common shift of the view. Views with exactly
    :data:`MIN_OWN_BBS` (one pose to spare) are judged against how far detections in views seeing six or more
    BBs lie from their neighbour's: more than twice that distribution's 99th percentile."""
    n = uv.shape[0]
    count = np.isfinite(uv).all(-1).sum(1)
    few = count <= max_bbs
    if n < 2 or not few.any():
        return np.zeros(uv.shape[:2], bool)
    nb = np.where(np.arange(n) > 0, np.arange(n) - 1, 1)
    guess = model.project(ViewState(state.R[nb], state.t[nb], state.k[nb]), xyz)
    d = uv - guess
    with np.errstate(invalid="ignore"):
        shift = np.nanmedian(d, axis=1, keepdims=True)
        off = np.linalg.norm(d - shift, axis=-1)
    tol = np.full(n, tol_px)
    ref = off[(count >= 6)[:, None] & np.isfinite(off)]
    if ref.size:  # the orbit's own frame-to-frame changes beyond a common shift (a wide panel sees rotations)
        tol[count == MIN_OWN_BBS] = max(tol_px, 2.0 * float(np.quantile(ref, 0.99)))
    with np.errstate(invalid="ignore"):
        return (off > tol[:, None]) & few[:, None] & np.isfinite(uv).all(-1)


History = list[tuple[NDArray[np.float64], NDArray[np.float64]]]


class Polish(NamedTuple):
    """Solve once more from ``start``, a previous outcome of :func:`_estimate` on the same detections, each residual
    divided by ``spread_of(uv)``: the detection's expected error relative to the others for detections ``(N, K, 2)``."""

    start: tuple[Any, ...]
    spread_of: Callable[[NDArray[np.float64]], NDArray[np.float64]]


def _min_observations(opt: CalibrationOptions, n_projections: int) -> int:
    """Frames a BB must be seen in: ``opt.min_observations``, by default 5 % of the projections and at least 8."""
    return opt.min_observations or max(8, int(0.05 * n_projections))


def _free_parameters(sub: ViewModel, xyz: NDArray[np.float64]) -> int:
    """What a bundle solve of the views ``sub`` and BB centres ``xyz`` fits: every view's parameters and every
    centre, less the seven of the similarity gauge (the centroid noise's degrees of freedom)."""
    return sub.n_params * sub.nominal.n_views + 3 * xyz.shape[0] - 7


def _polished(
    sub: ViewModel,
    uvs: NDArray[np.float64],
    start: tuple[Any, ...],
    ok: NDArray[np.bool_],
    placed: NDArray[np.bool_],
    spread: NDArray[np.float64],
    opt: CalibrationOptions,
    iters: int,
    record: Callable[[ViewState, NDArray[np.float64]], None],
) -> tuple[ViewState, NDArray[np.float64]]:
    """One bundle solve of the views ``sub`` (rows ``ok`` of all views) from a previous outcome of
    :func:`_estimate` ``start`` (its failed views from their nominal pose), with the Huber threshold fitted to that
    estimate's residuals."""
    full, xyz0 = start[2], start[1][placed]
    R = np.where(np.isfinite(full.R[ok]).all((1, 2))[:, None, None], full.R[ok], np.eye(3))
    st0 = ViewState(R, np.nan_to_num(full.t[ok]), full.k[ok])
    loss = opt.loss_scale_px
    if loss is None:
        resid = sub.geometry(st0).project(xyz0) - uvs
        loss = huber_threshold_px(centroid_noise_px(resid, _free_parameters(sub, xyz0)))
    res = bundle_adjust(sub, uvs, xyz0, st0, loss_scale_px=loss, max_iterations=iters, gauge_xyz=xyz0, spread=spread)
    record(res.state, res.xyz)
    return res.state, res.xyz


def _estimate(
    method: str,
    model: ViewModel,
    uv: NDArray[np.float64],
    opt: CalibrationOptions,
    progress: ProgressCallback | None,
    polish: Polish | None = None,
) -> tuple[ViewGeometry, NDArray[np.float64], ViewState, NDArray[np.float64], History, int, list[str], ViewQuality]:
    """Geometry of the projection views (NaN where failed), BB centres, states, cleaned uv, history, quality.
    With ``polish`` (its previous outcome from these detections, already cleaned of wrong blobs): one bundle solve
    from that solution instead of the first solve and its checks, its history and warnings continued, each residual
    divided by the detection's spread."""
    warnings: list[str] = []
    n = uv.shape[0]
    ok = usable_views(uv, opt.min_bbs_per_view)
    # a BB seen in fewer of the solved views than identification asks for is not placed: a few views far apart fit
    # any pairing of blobs, and views resting on such BBs calibrate as an island of their own, tens of px off
    min_obs = _min_observations(opt, n)
    placed = np.isfinite(uv[ok]).all(-1).sum(0) >= min_obs
    if not placed.all():
        warnings.append(
            f"{int((~placed).sum())} BB(s) seen in fewer than {min_obs} of the views to solve were left out "
            "(too few views to place them)"
        )
        uv = uv[:, placed]
        ok = usable_views(uv, opt.min_bbs_per_view)
    if ok.sum() < 2:
        raise NoMarkersError(
            f"only {int(ok.sum())} view(s) see {opt.min_bbs_per_view} or more BBs; nothing to calibrate"
        )
    sub = ViewModel(model.nominal[np.flatnonzero(ok)], model.intrinsics)
    uvs = uv[ok]
    history: History = []

    def record(state: ViewState, xyz: NDArray[np.float64]) -> None:
        g = sub.geometry(state)
        rpe = np.full(n, np.nan)
        rpe[ok] = rpe_per_frame(g, uvs, xyz)
        res = np.full(uv.shape[:2], np.nan)
        res[ok] = _residual_px(g, uvs, xyz)
        history.append((rpe, res))
        last = history[-1][0]
        report(progress, "estimate", len(history) - 1, iters, "", rpe_mean_mm=float(np.nanmean(last)))

    if method == "paper":
        iters = opt.iterations or 3
        state, xyz = paper_calibrate(sub, uvs, iterations=iters, callback=lambda i, s, x: record(s, x))
        n_iter = iters
    elif polish is not None:
        iters = opt.iterations or 30
        history.extend(polish.start[4])
        warnings.extend(polish.start[6])
        state, xyz = _polished(sub, uvs, polish.start, ok, placed, polish.spread_of(uv)[ok], opt, iters, record)
        n_iter = len(history) - 1
    else:
        iters = opt.iterations or 30
        xyz0 = triangulate_least_squares(*marker_rays(sub.nominal, uvs))
        record(sub.identity(), xyz0)
        res = bundle_adjust(
            sub,
            uvs,
            xyz0,
            loss_scale_px=opt.loss_scale_px or FIRST_LOSS_SCALE_PX,
            max_iterations=iters,
            callback=lambda i, s, x, c: record(s, x),
        )
        # detections far off the solution are wrong blobs: drop them and refine once more
        r = _residual_px(sub.geometry(res.state), uvs, res.xyz)
        fin = np.isfinite(r)
        sigma = 1.4826 * float(np.median(r[fin])) if fin.any() else 0.0
        bad = fin & (r > max(opt.outlier_px, 6.0 * sigma))
        n_bad = int(bad.sum())
        if n_bad:
            warnings.append(f"{n_bad} detection(s) off by more than {max(opt.outlier_px, 6 * sigma):.2f} px set to NaN")
        # a pose absorbs much of one wrong blob: test each detection against the pose fitted without it, and
        # views left with 4 BBs or fewer (too little redundancy to tell a wrong one) against the neighbouring
        # view: two wrong blobs among four can fit a wrong pose closely (experiment C at 512 px: 7 px off)
        bad |= _leave_one_out_outliers(
            sub, res.state, res.xyz, np.where(bad[..., None], np.nan, uvs), 1.5 * opt.outlier_px
        )
        bad |= _disagree_with_neighbour(
            sub, res.state, res.xyz, np.where(bad[..., None], np.nan, uvs), 3.0 * opt.outlier_px, max_bbs=MIN_OWN_BBS
        )
        if bad.sum() > n_bad:
            warnings.append(
                f"{int(bad.sum()) - n_bad} detection(s) disagree with their view fitted without them (or, "
                f"with {MIN_OWN_BBS} BBs or fewer, with the neighbouring view); set to NaN"
            )
        loss = opt.loss_scale_px
        if loss is None:  # the robust loss fitted to this scan's centroid noise, measured on the first solution
            clean = np.where(bad[..., None], np.nan, sub.geometry(res.state).project(res.xyz) - uvs)
            sigma = centroid_noise_px(clean, _free_parameters(sub, res.xyz))
            loss = huber_threshold_px(sigma)
        if bad.any() or loss != FIRST_LOSS_SCALE_PX:
            uvs = uvs.copy()
            uvs[bad] = np.nan
            uv = uv.copy()
            uv[ok] = uvs
            res = bundle_adjust(sub, uvs, res.xyz, res.state, loss_scale_px=loss, max_iterations=iters, gauge_xyz=xyz0)
            record(res.state, res.xyz)
        state, xyz = res.state, res.xyz
        n_iter = len(history) - 1
    full_state = ViewState.identity(n, model.n_intrinsics)
    full_state.R[ok], full_state.t[ok], full_state.k[ok] = state.R, state.t, state.k
    uv = uv.copy()
    uv[ok] = uvs
    in_bundle = np.zeros(n, bool)
    in_bundle[np.flatnonzero(ok)[usable_views(uvs, opt.min_bbs_per_view)]] = True
    if (~in_bundle).any() and in_bundle.any():
        # views outside the adjustment: keep only detections that agree with the neighbouring views' geometry
        guess = model.project(fill_states(full_state, in_bundle, n), xyz)
        off = (np.linalg.norm(guess - uv, axis=-1) > 3.0 * opt.outlier_px) & ~in_bundle[:, None]
        if off.any():
            uv[off] = np.nan
            warnings.append(
                f"{int(off.sum())} detection(s) in views outside the adjustment disagree with their "
                "neighbours and were set to NaN"
            )
    resid_xy = sub.geometry(state).project(xyz) - uvs
    noise = centroid_noise_px(resid_xy, _free_parameters(sub, xyz))
    paper = method == "paper"
    min_own = opt.min_bbs_per_view if paper else max(MIN_OWN_BBS, opt.min_bbs_per_view)
    fitted_state = full_state
    full_state, quality = assess_views(
        model, fitted_state, xyz, uv, noise_px=noise, min_own_bbs=min_own, max_gap=0 if paper else opt.bridge_max_views
    )
    if not paper and quality.inconsistent.any():
        fitted_state, uv, n_mended = _drop_single_misfits(model, fitted_state, xyz, uv, quality, min_own)
        if n_mended:
            warnings.append(
                f"{n_mended} view(s) fitted only without one detection that disagreed with the rest of "
                "the view; that detection was set to NaN"
            )
            full_state, quality = assess_views(
                model, fitted_state, xyz, uv, noise_px=noise, min_own_bbs=min_own, max_gap=opt.bridge_max_views
            )
    if quality.counts()["own"] == 0:
        raise NoMarkersError(
            f"no view sees the {MIN_OWN_BBS if not paper else opt.min_bbs_per_view} BBs it needs to be calibrated (and "
            f"checked) on its own: at most {int(quality.n_bbs.max(initial=0))} BBs per view; a pose fitted to 3 BBs "
            "has no redundancy and cannot be trusted. Tape more BBs on the object (6 to 10 are recommended)."
        )
    vec = model.geometry(
        ViewState(np.nan_to_num(full_state.R), np.nan_to_num(full_state.t), full_state.k)
    ).vectors.copy()
    vec[quality.status == FAILED] = np.nan
    return model.nominal.with_vectors(vec), xyz, full_state, uv, history, n_iter, warnings, quality


__all__ = [
    "METHODS",
    "CalibrationOptions",
    "CalibrationResult",
    "IterationStats",
    "calibrate_candidates",
    "calibrate_scan",
    "fill_states",
    "projected_diameter_px",
]
