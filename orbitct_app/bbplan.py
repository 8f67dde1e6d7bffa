"""A BB plan for one of the experiments' objects and an orbit, as the CLI (``orbitct plan bbs``) and the REST service
(``/plans/bbs``) make it: the placement, its prediction beside a hand-made spiral's and the experiment's own,
optionally the fewest BBs for a target accuracy, the JSON a person or the simulator (``--bbs-from``) reads, and its
picture."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from orbitct.progress import ProgressCallback, report, report_expected
from orbitct_app.bbplan_options import MAX_BBS, BBPlanOptions, checked_plan_options

#: samples of the orbit's motion errors a BB must be usable in (besides the nominal views) to count in a view
MOTION_SAMPLES = 3


class BBPlanError(ValueError):
    """The request cannot be planned (unknown orbit, BBs that do not fit, keep-out zones covering everything)."""


@dataclass(frozen=True)
class BBPlanRequest:
    """What to plan for: checked :class:`~orbitct_app.bbplan_options.BBPlanOptions` and the surface to tape the
    BBs on (``calib.surfaces.TapeSurface``, see :func:`load_surface`; None: the experiment's cylinder)."""

    options: BBPlanOptions
    surface: Any = None

    @classmethod
    def checked(cls, surface: Any = None, **options: Any) -> BBPlanRequest:
        """The request of keyword ``options`` (named as in :class:`~orbitct_app.bbplan_options.BBPlanOptions`) on
        ``surface``; BBPlanError naming each option that is wrong."""
        try:
            return cls(checked_plan_options(**options), surface)
        except ValueError as exc:
            raise BBPlanError(str(exc)) from None

    @classmethod
    def from_options(cls, options: BBPlanOptions, surface: Any = None) -> BBPlanRequest:
        """The request of ``options`` (a model that extends them, such as the REST request, is cut down to
        them) on ``surface``."""
        own = {name: getattr(options, name) for name in BBPlanOptions.model_fields}
        return cls(BBPlanOptions.model_validate(own), surface)

    @property
    def keep_out(self) -> tuple[Any, ...]:
        """The patches without BBs as ``calib.plan.KeepOut``."""
        from calib.plan import KeepOut

        return tuple(KeepOut(**zone.model_dump()) for zone in self.options.keep_out)


@dataclass
class BBPlan:
    """The plan as JSON-ready ``body`` plus what its picture needs."""

    body: dict[str, Any]
    placed: Any  # calib.plan.Placement
    own: Any  # calib.plan.PlanPrediction of the experiment's placement
    surface: Any
    warnings: list[str] = field(default_factory=list)
    spiral: Any = None  # calib.plan.PlanPrediction of a hand-made spiral of as many BBs (None: none to compare)


def _resolve(req: BBPlanRequest) -> tuple[str, Any, Any]:
    """The experiment's key, the orbit and the surface to tape on; BBPlanError naming what is wrong."""
    from calib.surfaces import EllipticCylinder
    from orbitct.orbits import OrbitError
    from orbitct.phantoms.experiments import BB_SURFACES
    from orbitct.simulator import resolve_orbit

    key = req.options.experiment  # checked by the options: one of BB_SURFACES
    try:
        orbit = resolve_orbit(key, req.options.orbit, req.options.frames)
    except OrbitError as exc:
        raise BBPlanError(str(exc)) from None
    return key, orbit, req.surface if req.surface is not None else EllipticCylinder(*BB_SURFACES[key])


def check_bb_plan_request(req: BBPlanRequest) -> dict[str, Any]:
    """What can be told of ``req`` in a moment (before seconds or minutes of planning): the experiment, the orbit,
    and that the keep-out patches leave room; ``{"experiment", "orbit", "views"}``, or BBPlanError naming what is
    wrong."""
    from calib.plan import check_room

    key, orbit, surface = _resolve(req)
    try:
        check_room(surface, req.keep_out)
    except ValueError as exc:
        raise BBPlanError(str(exc)) from None
    return {"experiment": key, "orbit": orbit.name, "views": int(orbit.n_frames)}


def make_bb_plan(req: BBPlanRequest, progress: ProgressCallback | None = None) -> BBPlan:
    """Plan the BBs for ``req`` (``progress`` hears ``prepare``, then ``duration`` with the expected time, then the
    search's stages ``count`` and ``plan``); BBPlanError with a one-line reason when it cannot."""
    from calib.background import PHOTON_FLOOR, SHIFT_FACTOR, SHIFT_SCATTER, phantom_background
    from calib.plan import (
        hand_spiral,
        metal_of,
        placement_score,
        plan_placement,
        predict_placement,
        suggest_bb_count,
    )
    from calib.quality import huber_threshold_px
    from calib.surfaces import polar_angle
    from orbitct.errorprofiles import make_profile
    from orbitct.phantoms.experiments import experiment_phantom
    from orbitct.simulator.bench import SimulatedBench

    started = time.perf_counter()
    o = req.options
    key, orbit, surface = _resolve(req)
    phantom = experiment_phantom(key)
    d = float(phantom.marker_diameter_mm or 3.0)
    geometry = SimulatedBench.with_panel(o.detector_px).nominal_geometry(orbit)
    metal = metal_of(phantom)
    report(progress, "prepare", 0, 2, f"what lies behind a BB on each of {geometry.n_views} views")
    background = phantom_background(phantom, geometry, surface)  # what lies behind each BB: photons, bone edges
    moved = (
        [make_profile(o.errors, seed).sample(orbit).apply_to_geometry(geometry) for seed in range(MOTION_SAMPLES)]
        if o.errors != "none"
        else []
    )
    options: dict[str, Any] = {
        "noise_px": o.noise_px,
        "metal": metal,
        "keep_out": req.keep_out,
        "seed": o.seed,
        "background": background,
        "moved": moved,
        "progress": progress,
    }
    report(progress, "prepare", 1, 2, "the experiment's own BBs predicted on every view")
    t_own = time.perf_counter()
    own = predict_placement(  # first: it also loads the kernels the time estimate measures
        geometry,
        phantom.markers_xyz,
        d,
        noise_px=o.noise_px,
        metal=metal,
        surface=surface,
        background=background,
        moved=moved,
    )
    t_own = time.perf_counter() - t_own
    report(progress, "prepare", 2, 2, "ready to search")
    expected_s = _expected_seconds(req, geometry, surface, d, options, started, t_own)
    warnings: list[str] = []
    n_bbs, suggestion = o.bbs, None
    try:
        if o.target_px is not None:
            suggestion = suggest_bb_count(geometry, surface, d, o.target_px, n_max=o.max_bbs, **options)
            if suggestion.n_bbs is None:
                n_bbs = max(suggestion.tried, default=o.bbs)
                warnings.append(
                    f"no placement of up to {o.max_bbs} BBs reaches {o.target_px:g} px in every view; "
                    f"planned {n_bbs} BBs, the most that fit"
                )
            else:
                n_bbs = suggestion.n_bbs
        placed = plan_placement(geometry, surface, n_bbs, d, **options)
    except ValueError as exc:
        raise BBPlanError(str(exc)) from None
    try:
        spiral: Any = predict_placement(
            geometry,
            hand_spiral(surface, n_bbs, d, seed=o.seed, keep_out=req.keep_out),
            d,
            noise_px=o.noise_px,
            metal=metal,
            surface=surface,
            background=background,
            moved=moved,
        )
    except ValueError:  # the spiral leaves the surface or enters a keep-out zone: none to compare with
        spiral = None
    pred = placed.prediction
    polar_deg = np.degrees(polar_angle(surface, placed.angle_rad, placed.z_mm))  # where a person finds each BB
    if pred.under_determined.size:
        warnings.append(
            f"{pred.under_determined.size} view(s) see fewer than 4 usable BBs (first: "
            f"{pred.under_determined[:8].tolist()}); more BBs, or another orbit"
        )
    body: dict[str, Any] = {
        "experiment": key,
        "orbit": orbit.name,
        "views": int(geometry.n_views),
        "detector_px": o.detector_px,
        "bb_diameter_mm": d,
        "noise_px": o.noise_px,
        "motion_errors": {"profile": o.errors, "samples": len(moved)},
        "noise_model": {
            "background": f"experiment {key}'s phantom",
            "photon_floor": PHOTON_FLOOR,
            "shift_factor": SHIFT_FACTOR,
            "shift_scatter": SHIFT_SCATTER,
            "huber_threshold_px": huber_threshold_px(o.noise_px),
        },
        "surface": surface.describe(),
        "keep_out": [vars(z) for z in req.keep_out],
        "bbs": [
            {
                "number": k + 1,
                "xyz_mm": [round(float(v), 2) for v in placed.xyz[k]],
                "angle_deg": round(float(polar_deg[k]) % 360.0, 1),
                "height_mm": round(float(placed.z_mm[k]), 1),
            }
            for k in range(n_bbs)
        ],
        "predicted": pred.summary(),
        "score": placed.score,
        "experiment_placement": {
            "bbs": int(phantom.n_markers),
            "predicted": own.summary(),
            "score": placement_score(own),
        },
        "hand_spiral": None
        if spiral is None
        else {"bbs": n_bbs, "predicted": spiral.summary(), "score": placement_score(spiral)},
        "per_view": {
            "n_bbs": pred.n_bbs.tolist(),
            "predicted_px": [None if not np.isfinite(v) else round(float(v), 4) for v in pred.predicted_px],
        },
        "warnings": warnings,
        "time": {"expected_s": round(expected_s, 2), "elapsed_s": round(time.perf_counter() - started, 2)},
    }
    if suggestion is not None:
        body["count_suggestion"] = {
            "target_px": suggestion.target_px,
            "n_bbs": suggestion.n_bbs,
            "tried": {str(n): s for n, s in suggestion.tried.items()},
        }
    return BBPlan(_json_ready(body), placed, own, surface, warnings, spiral)


def _expected_seconds(
    req: BBPlanRequest,
    geometry: Any,
    surface: Any,
    diameter_mm: float,
    options: dict[str, Any],
    started: float,
    full_prediction_s: float,
) -> float:
    """The whole plan's expected seconds from ``started``: what it took so far, the search as measured on this
    machine now (:func:`calib.plan.placement_cost`), and two more predictions on every view (the plan's and the
    spiral's, each as long as ``full_prediction_s``); said to ``options["progress"]`` as stage ``duration``."""
    from calib.plan import placement_cost
    from calib.quality import MIN_OWN_BBS

    o = req.options
    n_probe = o.bbs if o.target_px is None else o.max_bbs
    cost = placement_cost(geometry, surface, n_probe, diameter_mm, **options)
    if o.target_px is None:
        search_s, at_most = cost.search_s(o.bbs), False
    else:  # every count tried, then the one found planned in full: at most
        search_s, at_most = cost.count_s(MIN_OWN_BBS, o.max_bbs) + cost.search_s(o.max_bbs), True
    expected = time.perf_counter() - started + search_s + 2 * full_prediction_s
    report_expected(options.get("progress"), "planning", expected, at_most=at_most)
    return expected


def _json_ready(value: Any) -> Any:
    """``value`` with NaN and infinities as None and numpy scalars as Python numbers (valid JSON throughout)."""
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off")


def load_surface(source: str, threshold_per_mm: float | None = None) -> Any:
    """The object's outer surface for the planner: a shape by parameters (``cylinder:...``, ``ellipsoid:...``, see
    ``calib.surfaces.shape_from_text``), or a real object's outline (``calib.surfaces.Outline``) from a surface mesh
    (``.stl``, ``.obj``, ``.ply``, ``.off``; mm, object frame), a prior volume as NIfTI (``.nii``, ``.nii.gz``; as
    ``orbitct`` writes it: axis-aligned, mm) or a reconstruction in a scan file (``SCAN.h5#NAME``), thresholded at
    ``threshold_per_mm`` (default: Otsu's threshold of the volume). BBPlanError naming what is wrong."""
    from calib.surfaces import Outline, shape_from_text

    if source.startswith(("cylinder:", "ellipsoid:")):
        try:
            return shape_from_text(source)
        except ValueError as exc:
            raise BBPlanError(f"surface {exc}") from None
    path_text, _, recon = source.partition("#")
    path = Path(path_text)
    name = path.name.lower()
    if not path.is_file():
        raise BBPlanError(
            f"surface {source!r}: no such file (a shape is cylinder:R,ZMIN:ZMAX, cylinder:A,B,ZMIN:ZMAX "
            "or ellipsoid:A,B,C[,ZMIN:ZMAX], mm)"
        )
    try:
        if name.endswith(MESH_SUFFIXES):
            import trimesh

            mesh = trimesh.load(str(path), force="mesh")
            if len(getattr(mesh, "faces", [])) == 0:
                raise BBPlanError(f"surface {source!r}: no triangles in the mesh")
            points, _ = trimesh.sample.sample_surface(mesh, 200_000, seed=0)
            return Outline.from_points(np.asarray(points), source=path.name)
        if name.endswith((".nii", ".nii.gz")):
            import nibabel as nib

            img: Any = nib.load(str(path))  # a NIfTI image: affine and voxels
            affine = np.asarray(img.affine)
            if not np.allclose(affine[:3, :3], np.diag(np.diag(affine[:3, :3]))) or (np.diag(affine)[:3] <= 0).any():
                raise BBPlanError(
                    f"surface {source!r}: the volume's axes must be the object frame's x, y, z (a diagonal, "
                    "positive affine, as orbitct writes it)"
                )
            volume = np.transpose(np.asarray(img.dataobj, dtype=np.float32), (2, 1, 0))
            voxel = (float(affine[0, 0]), float(affine[1, 1]), float(affine[2, 2]))
            origin = (float(affine[0, 3]), float(affine[1, 3]), float(affine[2, 3]))
        elif name.endswith((".h5", ".hdf5")) and recon:
            from orbitct.scanfile import ScanFile, ScanFileError

            try:
                with ScanFile(path) as sf:
                    volume, attrs = sf.read_recon(recon)
            except ScanFileError as exc:
                raise BBPlanError(f"surface {source!r}: {exc}") from None
            voxel, origin = tuple(attrs["voxel_mm"]), tuple(attrs["origin_mm"])
        else:
            raise BBPlanError(
                f"surface {source!r}: expected a mesh ({', '.join(MESH_SUFFIXES)}), a NIfTI volume "
                "(.nii, .nii.gz) or SCAN.h5#RECONSTRUCTION"
            )
        return outline_from_volume(
            volume, voxel, origin, threshold_per_mm, f"{path.name}{'#' + recon if recon else ''}"
        )
    except BBPlanError:
        raise
    except ValueError as exc:
        raise BBPlanError(f"surface {source!r}: {exc}") from None


def outline_from_volume(
    volume: np.ndarray,
    voxel_mm: Sequence[float],
    origin_mm: Sequence[float],
    threshold_per_mm: float | None,
    source: str,
) -> Any:
    """The outer surface of the voxels of a prior volume (nz, ny, nx; 1/mm) above ``threshold_per_mm`` (default:
    Otsu's threshold); BBPlanError when nothing is above it."""
    from calib.surfaces import Outline

    volume = np.nan_to_num(np.asarray(volume, dtype=np.float32))
    level = threshold_per_mm if threshold_per_mm is not None else _otsu(volume)
    try:
        voxel = (float(voxel_mm[0]), float(voxel_mm[1]), float(voxel_mm[2]))
        origin = (float(origin_mm[0]), float(origin_mm[1]), float(origin_mm[2]))
        return Outline.from_mask(volume > level, voxel, origin, source=f"{source} > {level:.4g}/mm")
    except ValueError as exc:
        raise BBPlanError(f"surface {source!r}: {exc}") from None


def _otsu(volume: np.ndarray) -> float:
    """Otsu's threshold: the level that best separates the histogram into two classes (air and object)."""
    hist, edges = np.histogram(volume, bins=256)
    centres = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    with np.errstate(invalid="ignore", divide="ignore"):
        between = w0 * w1 * (m0 / w0 - (m0[-1] - m0) / w1) ** 2
    return float(centres[int(np.nanargmax(between[:-1]))])


def write_bb_plan(plan: BBPlan, out: Path) -> Path:
    """Write the plan's JSON to ``out`` and its picture beside it (``.png``); the picture's path."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(plan.body, indent=1))
    picture = out.with_suffix(".png")
    _picture(picture, plan)
    return picture


#: a BB of a plan file lies within this distance of the isocentre (mm): taped on the object, never beyond it
PLAN_REACH_MM = 500.0


def read_bb_plan(path: Path) -> tuple[str | None, np.ndarray, float]:
    """The experiment (None when the file names none), BB centres ``(K, 3)`` (mm) and BB diameter (mm) of a plan's
    JSON (as :func:`write_bb_plan` writes it, or by hand: ``{"bb_diameter_mm": D, "bbs": [{"xyz_mm": [x, y, z]},
    ...]}``); BBPlanError naming what is wrong."""
    why = "write one with `orbitct plan bbs`"
    try:
        body = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise BBPlanError(
            f"{path}: cannot read it ({exc.strerror if isinstance(exc, OSError) else 'not text'})"
        ) from None
    except ValueError as exc:
        raise BBPlanError(f"{path}: not JSON ({exc}); {why}") from None
    if not isinstance(body, dict) or not isinstance(body.get("bbs"), list):
        raise BBPlanError(f"{path}: not a BB plan (an object with a list 'bbs' of {{'xyz_mm': [x, y, z]}}); {why}")
    d = body.get("bb_diameter_mm")
    if isinstance(d, bool) or not isinstance(d, int | float) or not 0.0 < d <= 50.0:
        raise BBPlanError(f"{path}: bb_diameter_mm must be a number of mm in (0, 50], got {d!r}")
    if not 1 <= len(body["bbs"]) <= MAX_BBS:
        raise BBPlanError(f"{path}: a plan has 1 to {MAX_BBS} BBs, this one {len(body['bbs'])}")
    xyz = np.empty((len(body["bbs"]), 3))
    for k, bb in enumerate(body["bbs"]):
        v = bb.get("xyz_mm") if isinstance(bb, dict) else None
        if (
            not isinstance(v, list)
            or len(v) != 3
            or not all(isinstance(c, int | float) and not isinstance(c, bool) for c in v)
        ):
            raise BBPlanError(f"{path}: BB {k + 1} needs xyz_mm as three numbers (mm), got {v!r}")
        xyz[k] = v
    reach = np.where(np.isfinite(xyz).all(1), np.linalg.norm(xyz, axis=1), np.inf)
    far = np.flatnonzero(reach > PLAN_REACH_MM)
    if far.size:
        raise BBPlanError(
            f"{path}: BB {far[0] + 1} at {xyz[far[0]].tolist()} mm is not within {PLAN_REACH_MM:g} mm of "
            "the isocentre (finite numbers, in mm)"
        )
    gap = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1) + np.diag(np.full(len(xyz), np.inf))
    if (gap < d).any():
        i, j = np.unravel_index(np.argmin(gap), gap.shape)
        raise BBPlanError(
            f"{path}: BBs {min(i, j) + 1} and {max(i, j) + 1} are {gap[i, j]:.1f} mm apart: BBs of {d:g} mm "
            "cannot overlap"
        )
    experiment = body.get("experiment")
    return (str(experiment) if experiment is not None else None), xyz, float(d)


def plan_lines(plan: BBPlan) -> list[str]:
    """The plan as a person reads it at the table: the BBs, then the prediction beside a hand-made spiral's and the
    experiment's own."""
    b = plan.body
    lines = [
        f"{b['experiment']}, orbit {b['orbit']} ({b['views']} views), {len(b['bbs'])} BBs of {b['bb_diameter_mm']:g} "
        f"mm, centroid noise {b['noise_px']:g} px, motion errors {b['motion_errors']['profile']}"
    ]
    if "count_suggestion" in b:
        c = b["count_suggestion"]
        lines.append(
            f"  fewest BBs for {c['target_px']:g} px in every view: {c['n_bbs'] if c['n_bbs'] else 'not reached'} "
            f"(worst view by count: "
            + ", ".join(f"{n}: {s['predicted_px_max']:.3f}" for n, s in c["tried"].items())
            + ")"
        )
    lines.append("  BB  angle deg  height mm   x mm    y mm    z mm")
    for bb in b["bbs"]:
        x, y, z = bb["xyz_mm"]
        lines.append(
            f"  {bb['number']:>2}  {bb['angle_deg']:9.1f}  {bb['height_mm']:9.1f}  {x:6.1f}  {y:6.1f}  {z:6.1f}"
        )
    compared = [("planned", b["predicted"], len(b["bbs"]))]
    if b.get("hand_spiral"):
        compared.append(("a hand-made spiral", b["hand_spiral"]["predicted"], b["hand_spiral"]["bbs"]))
    compared.append(("the experiment's own", b["experiment_placement"]["predicted"], b["experiment_placement"]["bbs"]))
    for name, s, n in compared:
        lines.append(
            f"  {name} ({n} BBs): predicted error median {s['predicted_px_median']:.3f} px, worst "
            f"{s['predicted_px_max']:.3f} px; usable BBs per view at least {s['bbs_min']}, median "
            f"{s['bbs_median']:g}; {s['under_determined']} view(s) under-determined"
        )
    if "time" in b:  # plans written before it have none
        lines.append(f"  time: {b['time']['elapsed_s']:.1f} s (expected {b['time']['expected_s']:.1f} s)")
    return lines


def _picture(path: Path, plan: BBPlan) -> None:
    """The object with the BBs and their numbers (in 3-D, and unrolled with the keep-out zones); BBs per view and
    the predicted error along the orbit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import MultipleLocator

    placed, own, surface = plan.placed, plan.own, plan.surface
    fig = plt.figure(figsize=(15, 4.6))
    ax3 = fig.add_subplot(1, 3, 1, projection="3d")
    ax0, ax1 = fig.add_subplot(1, 3, 2), fig.add_subplot(1, 3, 3)
    _object_3d(ax3, surface, placed.xyz, plan.body["keep_out"])
    for zone in plan.body["keep_out"]:
        a0, a1 = zone["angle_from_deg"], zone["angle_to_deg"]
        spans = [(a0, a1)] if a1 > a0 else [(a0, 360.0), (0.0, a1)]
        for lo, hi in spans:
            ax0.add_patch(
                Rectangle(
                    (lo, zone["z_min_mm"]),
                    hi - lo,
                    zone["z_max_mm"] - zone["z_min_mm"],
                    color="grey",
                    alpha=0.3,
                    label=None,
                )
            )
    polar_deg = [bb["angle_deg"] for bb in plan.body["bbs"]]
    ax0.scatter(polar_deg, placed.z_mm, s=60, c="tab:red")
    for k, (a, z) in enumerate(zip(polar_deg, placed.z_mm, strict=True)):
        ax0.annotate(str(k + 1), (a, z), textcoords="offset points", xytext=(5, 5))
    ax0.set(
        xlim=(0, 360),
        ylim=(surface.z_min_mm - 5, surface.z_max_mm + 5),
        xlabel="angle on the object (deg, from +x)",
        ylabel="height (mm)",
        title="unrolled" + (" (grey: keep out)" if plan.body["keep_out"] else ""),
    )
    ax0.xaxis.set_major_locator(MultipleLocator(45))
    ax0.grid(alpha=0.3)
    views = np.arange(placed.prediction.n_bbs.size)
    ax1.plot(views, placed.prediction.predicted_px, label="planned: predicted error (px)")
    if plan.spiral is not None:
        ax1.plot(views, plan.spiral.predicted_px, label="a hand-made spiral", alpha=0.7)
    ax1.plot(views, own.predicted_px, label="experiment's placement", alpha=0.7)
    ax1.set(xlabel="view", ylabel="predicted error (px)", title="calibration accuracy along the orbit")
    ax1b = ax1.twinx()
    ax1b.step(views, placed.prediction.n_bbs, color="grey", alpha=0.4, where="mid")
    ax1b.set_ylabel("usable BBs (planned)")
    counts = placed.prediction.n_bbs
    if counts.size:  # whole BBs only
        lo, hi = int(counts.min()), int(counts.max())
        ax1b.set_ylim(lo - 0.5, hi + 0.5)
        ax1b.set_yticks(np.arange(lo, hi + 1, max(1, -(-(hi - lo) // 6))))
    ax1.legend(loc="upper left", fontsize=8)
    b = plan.body
    fig.suptitle(
        f"experiment {b['experiment']}: {len(b['bbs'])} BBs of {b['bb_diameter_mm']:g} mm, orbit {b['orbit']} "
        f"({b['views']} views)"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _object_3d(ax: Any, surface: Any, xyz: np.ndarray, keep_out: list[dict[str, float]]) -> None:
    """The tape surface as rings and lines, the keep-out zones' borders, the BBs with their numbers (pale behind the
    object as seen), and the object frame's +x (angle 0) and +z."""
    from matplotlib.ticker import MaxNLocator

    from calib.plan import KeepOut
    from calib.surfaces import address_angle

    z_lo, z_hi = surface.z_min_mm, surface.z_max_mm
    for zone in keep_out:  # its border on the surface (in polar angles): two arcs and two edges
        a0 = np.radians(zone["angle_from_deg"])
        span = np.radians(KeepOut(**zone).span_deg)
        arc = a0 + np.linspace(0.0, span, 60)
        z0, z1 = max(zone["z_min_mm"], z_lo), min(zone["z_max_mm"], z_hi)
        side = np.linspace(z0, z1, 20)
        edges = [(address_angle(surface, arc, z), np.full(arc.size, z)) for z in (z0, z1)]
        edges += [
            (np.array([address_angle(surface, np.array([a]), z)[0] for z in side]), side) for a in (a0, a0 + span)
        ]
        for a, z in edges:
            ax.plot(*surface.points(a, z, 0.0).T, color="black", lw=1.2, alpha=0.6)
    turn = np.radians(np.arange(0.0, 361.0, 4.0))
    for z in np.linspace(z_lo, z_hi, 6):
        ring = surface.points(turn, np.full(turn.size, z), 0.0)
        ring[~surface.covers(turn, np.full(turn.size, z))] = np.nan
        ax.plot(*ring.T, color="grey", lw=0.6, alpha=0.5)
    heights = np.linspace(z_lo, z_hi, 24)
    for a in address_angle(surface, np.radians(np.arange(0.0, 360.0, 30.0)), 0.5 * (z_lo + z_hi)):  # every 30 deg
        line = surface.points(np.full(heights.size, a), heights, 0.0)
        line[~surface.covers(np.full(heights.size, a), heights)] = np.nan
        ax.plot(*line.T, color="grey", lw=0.6, alpha=0.5)
    elev, azim = 20.0, -60.0
    ax.view_init(elev=elev, azim=azim)
    toward = np.array([np.cos(np.radians(azim)), np.sin(np.radians(azim))])  # the eye's side, seen from above
    front = xyz[:, :2] @ toward >= 0.0
    for k, p in enumerate(xyz):
        ax.scatter(*p, s=50, c="tab:red", alpha=1.0 if front[k] else 0.35, depthshade=False)
        ax.text(*(p + [0.0, 0.0, 6.0]), str(k + 1), fontsize=9, alpha=1.0 if front[k] else 0.5)
    reach = 1.3 * float(np.nanmax(np.hypot(xyz[:, 0], xyz[:, 1]))) if len(xyz) else 100.0
    ax.quiver(0, 0, z_lo, reach, 0, 0, color="tab:blue", arrow_length_ratio=0.1)
    ax.text(reach, 0, z_lo, "+x (0 deg)", color="tab:blue", fontsize=8)
    ax.quiver(0, 0, z_hi, 0, 0, 0.3 * (z_hi - z_lo), color="tab:blue", arrow_length_ratio=0.2)
    ax.text(0, 0, z_hi + 0.35 * (z_hi - z_lo), "+z", color="tab:blue", fontsize=8)
    ax.set(
        xlabel="x (mm)",
        ylabel="y (mm)",
        zlabel="z (mm)",
        title="where to tape the BBs" + (" (pale: behind; black: keep out)" if keep_out else " (pale: behind)"),
    )
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_major_locator(MaxNLocator(4))
    ax.set_box_aspect((1.0, 1.0, max(0.4, (z_hi - z_lo) / (2 * reach / 1.3))))
