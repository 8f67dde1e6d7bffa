"""Benchmark: does the BB planner's predicted accuracy rank and match the measured calibration accuracy?

Random placements of 4 to 10 BBs on experiment A's cylinder, on two orbits (sawtooth, and DCArc: a double
circle plus an arc), each simulated (bench error profile), calibrated with ``orbitct calibrate`` (bundle) and
measured against the truth (RMS px over field-of-view points after similarity alignment, views calibrated from
their own BBs; the calibration runs with its default check, as a user runs it, and a result that fails it is
marked). The prediction (``calib.plan.predict_placement``, nominal views, nothing rendered, the cylinder's
outline for its silhouette edge; by default also the phantom as the object's background, see
``calib.background``) uses one centroid noise for every case: the one measured on the first case's
calibration (a lab measures it once per detector and BB size). Prints each case, the Spearman rank correlation,
the share within a factor of 1.5, and the prediction's time for 500 views and 10 BBs. Then, per experiment,
hand-made spirals like the published placement against planned placements with as many BBs (one plan per seed),
and the experiment's own placement beside them (three seeds each by default, ``--seeds``; frames scaled like the paper's 500 / 656 / 857;
``--frames 500``: the paper's counts). For each, how far its detections lie from the truth and what the same BBs
in the same views reach from their true projections plus one independent noise for all (the placement's geometry
alone, ``calib.evaluate.truth_fed_error_px``): what a plan gains by its geometry and what by its detections.

    python benchmarks/bb_planning.py                 # 256 px, 120 frames, 10 placements per orbit
    python benchmarks/bb_planning.py --placements 4  # quicker
    python benchmarks/bb_planning.py --placements 0 --size 512 --compare A,B,C   # only the comparison
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

import numpy as np
from machine_info import describe_machine

ORBITS = ("sawtooth", "dcarc")


def _placement(rng: np.random.Generator, k: int, radius_mm: float, half_height_mm: float) -> np.ndarray:
    """``k`` BB centres on a z-cylinder's surface, at least 25 mm apart."""
    out: list[np.ndarray] = []
    while len(out) < k:
        a, z = rng.uniform(0, 2 * np.pi), rng.uniform(-half_height_mm, half_height_mm)
        c = np.array([radius_mm * np.cos(a), radius_mm * np.sin(a), z])
        if all(np.linalg.norm(c - o) >= 25.0 for o in out):
            out.append(c)
    return np.array(out)


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


def _case(
    work: Path, key: str, orbit: str | None, frames: int, xyz: np.ndarray, size: int, seed: int, layout_seed: int
) -> dict[str, Any]:
    """Experiment ``key``'s object (layout ``layout_seed``) with BBs ``xyz``, simulated on ``orbit`` (None: the
    experiment's) with the bench errors and noise of ``seed``, calibrated and measured against the truth: the error
    over the views calibrated from their own BBs and over every calibrated view, the centroid noise, the views."""
    import calib
    from calib.evaluate import similarity_aligned_error_px, truth_fed_error_px
    from orbitct.errorprofiles import make_profile
    from orbitct.phantoms.experiments import experiment_phantom
    from orbitct.scanfile import ScanFile
    from orbitct.simulator import resolve_orbit
    from orbitct.simulator.scan import simulate_scan

    phantom = experiment_phantom(key, layout_seed).with_markers(xyz)
    path = work / f"{key}_{orbit}_{seed}.h5"
    simulate_scan(
        phantom,
        resolve_orbit(key, orbit, frames),
        out=path,
        detector_px=size,
        seed=seed,
        overwrite=True,
        errors=make_profile("bench", seed, angle_scale=frames / 500.0),
    )
    try:
        res = calib.calibrate_scan(path, diameter_mm=phantom.marker_diameter_mm)  # the default check, as a user runs it
    except calib.CalibrationError as exc:
        path.unlink()
        return {"measured_px": float("nan"), "valid_px": float("nan"), "why": str(exc)[:80]}
    with ScanFile(path) as sf:
        proj = sf.projection_indices
        truth, nominal = sf.geometry("truth")[proj], sf.geometry("nominal")[proj]
        truth_xyz = sf.truth_markers_xyz()
    path.unlink()
    geometry = res.geometry[proj]
    own = np.flatnonzero(res.view_status[proj] == 0)
    valid = np.flatnonzero(geometry.valid)

    def error(views: np.ndarray) -> float:
        return float(similarity_aligned_error_px(geometry[views], truth[views])[0]) if views.size >= 2 else float("nan")

    noise = float(res.quality.attrs()["centroid_noise_px"]) if res.quality is not None else float("nan")
    # the placement's geometry alone: the same BBs in the same views from their true projections plus one noise
    # for every case; and how far the detections themselves lie from the truth
    geometry_px, detection_px = truth_fed_error_px(res.uv[proj], truth, truth_xyz, nominal, GEOMETRY_NOISE_PX, seed)
    return {
        "measured_px": error(own),
        "valid_px": error(valid),
        "noise_px": noise,
        "nominal": nominal,
        "own": own,
        "geometry_px": geometry_px,
        "detection_px": detection_px,
        "passed": res.quality is not None and res.quality.passed,
        "why": "",
    }


PAPER_FRAMES = {"A": 500, "B": 656, "C": 857}
#: the noise (px per axis) fed with the true projections for a placement's geometry alone
GEOMETRY_NOISE_PX = 0.1


def _planned_against_spiral(args: Any, noise: float | None) -> None:
    """Hand-made spirals like the published one (``calib.plan.hand_spiral``, one per seed) against ``orbitct plan
    bbs``' placement with as many BBs (planned anew per seed: the search is random too), and the experiment's own
    placement (A: such a spiral; B: the Cho phantom's two designed rings; C: BBs taped at random), each simulated
    over ``args.seeds`` seeds (errors and noise) and calibrated: predicted and measured error side by side, and the views
    each leaves under-determined (predicted)."""
    from calib.background import phantom_background
    from calib.plan import hand_spiral, metal_of, plan_placement, predict_placement
    from calib.surfaces import EllipticCylinder
    from orbitct.phantoms.experiments import BB_SURFACES, experiment_phantom
    from orbitct.simulator import resolve_orbit
    from orbitct.simulator.bench import SimulatedBench

    print(
        "\n| experiment | placement | BBs | views | under-determined views (predicted, per seed) | predicted px (mean) | "
        f"measured px ({args.seeds} seeds) | mean | detections vs truth, px per axis (mean) | geometry alone: true projections + "
        f"{GEOMETRY_NOISE_PX:g} px (mean) |\n|---|---|---|---|---|---|---|---|---|---|"
    )
    changes = []
    for key in [k.strip().upper() for k in args.compare.split(",") if k.strip()]:
        ph = experiment_phantom(key)
        frames = int(round(args.frames * PAPER_FRAMES[key] / 500))
        d = float(ph.marker_diameter_mm)
        g = SimulatedBench.with_panel(args.size).nominal_geometry(resolve_orbit(key, None, frames))
        surface = EllipticCylinder(*BB_SURFACES[key])
        background = phantom_background(ph, g, surface) if args.background else None
        t0 = time.perf_counter()
        planned = [
            plan_placement(
                g, surface, ph.n_markers, d, noise_px=noise or 0.1, metal=metal_of(ph), seed=seed, background=background
            ).xyz
            for seed in range(args.seeds)
        ]
        print(
            f"| {key} | (planning: {(time.perf_counter() - t0) / args.seeds:.0f} s per plan) | | | | | | | | |",
            flush=True,
        )
        placements = {
            "hand spiral": [hand_spiral(surface, ph.n_markers, d, seed=seed) for seed in range(args.seeds)],
            "planned": planned,
            "experiment's own": [ph.markers_xyz] * args.seeds,
        }
        means, alone = {}, {}
        for name, per_seed in placements.items():
            preds = [
                predict_placement(
                    g, xyz, d, noise_px=noise or 0.1, metal=metal_of(ph), surface=surface, background=background
                )
                for xyz in per_seed
            ]
            under = [p.under_determined.size for p in preds]
            predicted = np.mean([p.summary()["predicted_px_rms"] for p in preds])
            errs, marks, detection, geometry = [], [], [], []
            with tempfile.TemporaryDirectory() as work:
                for seed, xyz in enumerate(per_seed):
                    case = _case(Path(work), key, None, frames, xyz, args.size, seed, layout_seed=0)
                    errs.append(case["valid_px"])
                    marks.append("" if case.get("passed") else " (check failed)")
                    detection.append(case.get("detection_px", float("nan")))
                    geometry.append(case.get("geometry_px", float("nan")))
            means[name], alone[name] = float(np.nanmean(errs)), float(np.nanmean(geometry))
            print(
                f"| {key} | {name} | {ph.n_markers} | {frames} | {' / '.join(map(str, under))} | {predicted:.3f} | "
                f"{' / '.join(f'{e:.3f}{m}' for e, m in zip(errs, marks, strict=True))} | {means[name]:.3f} | "
                f"{np.nanmean(detection):.3f} | {alone[name]:.3f} |",
                flush=True,
            )
        changes.append(100 * (means["planned"] / means["hand spiral"] - 1))
        print(
            f"| {key} | planned vs hand spiral | | | | | | {changes[-1]:+.0f} % | | "
            f"{100 * (alone['planned'] / alone['hand spiral'] - 1):+.0f} % |",
            flush=True,
        )
        own_change = 100 * (means["planned"] / means["experiment's own"] - 1)
        print(f"| {key} | planned vs the experiment's own | | | | | | {own_change:+.0f} % | | |", flush=True)
    if changes:
        print(
            f"\nplanned vs hand spiral, mean over the experiments: {np.mean(changes):+.0f} % (target: -30 % or better)"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="detector pixels per side")
    ap.add_argument("--frames", type=int, default=120, help="projections")
    ap.add_argument("--placements", type=int, default=10, help="random placements per orbit (0: skip the ranking)")
    ap.add_argument("--compare", default="A,B,C", help="experiments whose own placement is compared with a planned one")
    ap.add_argument("--seeds", type=int, default=3, help="seeds (placements, errors and noise) per compared placement")
    ap.add_argument(
        "--background",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="plan and predict with the object's background (photons and structure under each BB; the "
        "experiment's phantom as the prior model of the object)",
    )
    args = ap.parse_args()
    from calib.background import phantom_background
    from calib.plan import predict_placement
    from calib.surfaces import EllipticCylinder
    from orbitct.phantoms.experiments import BB_SURFACES, experiment_phantom

    print(describe_machine())
    print(
        f"experiment A's cylinder, {args.size} px, {args.frames} frames, bench errors; 1-min load at start "
        f"{os.getloadavg()[0]:.2f}\n"
    )
    d = float(experiment_phantom("A").marker_diameter_mm or 3.17)
    rng = np.random.default_rng(7)
    surface = EllipticCylinder(*BB_SURFACES["A"])
    rows = []
    noise = None
    with tempfile.TemporaryDirectory() as work:
        for orbit in ORBITS:
            for i in range(args.placements):
                k = int(rng.choice([4, 5, 6, 8, 10]))
                xyz = _placement(rng, k, 75.0 + d / 2, 80.0)
                case = _case(Path(work), "A", orbit, args.frames, xyz, args.size, 100 + i, layout_seed=100 + i)
                if not np.isfinite(case["measured_px"]):
                    rows.append((orbit, k, float("nan"), float("nan"), f"refused: {case['why']}"))
                    continue
                noise = noise if noise is not None else case["noise_px"]
                background = (
                    phantom_background(experiment_phantom("A", 100 + i), case["nominal"], surface)
                    if args.background
                    else None
                )
                pred = predict_placement(
                    case["nominal"], xyz, d, noise_px=noise, surface=surface, background=background
                )
                p = pred.predicted_px[case["own"]]
                predicted = float(np.sqrt(np.nanmean(p**2)))
                rows.append((orbit, k, predicted, case["measured_px"], "" if case["passed"] else "(check failed)"))
    if rows:
        print(f"centroid noise used for every prediction (measured on the first case): {noise:.3f} px\n")
        print("| orbit | BBs | predicted px | measured px | ratio |\n|---|---|---|---|---|")
        for orbit, k, pr, me, why in rows:
            ratio = pr / me if np.isfinite(pr) and me > 0 else float("nan")
            print(f"| {orbit} | {k} | {pr:.3f} | {me:.3f} | {ratio:.2f} |" + (f" {why}" if why else ""))
        ok = [(pr, me) for _, _, pr, me, _ in rows if np.isfinite(pr) and np.isfinite(me)]
        pr_a, me_a = np.array([o[0] for o in ok]), np.array([o[1] for o in ok])
        within = float(np.mean((pr_a / me_a <= 1.5) & (me_a / pr_a <= 1.5))) if ok else float("nan")
        print(
            f"\nSpearman rank correlation {_spearman(pr_a, me_a):.2f} over {len(ok)} cases (target >= 0.8); "
            f"within a factor of 1.5: {100 * within:.0f} % (target >= 90 %)"
        )
    _planned_against_spiral(args, noise)
    from orbitct.geometry import ViewGeometry
    from orbitct.reference_bench import reference_panel

    t = np.linspace(0, 2 * np.pi, 500, endpoint=False)
    g = ViewGeometry.from_carm(t, np.radians(20) * np.sin(2 * t), 785.0, 1200.0, reference_panel(768))
    xyz = _placement(np.random.default_rng(1), 10, 75.0 + d / 2, 80.0)
    predict_placement(g, xyz, d, surface=surface)  # first call loads the compiled kernels
    t0 = time.perf_counter()
    for _ in range(20):
        predict_placement(g, xyz, d, surface=surface)
    print(f"prediction time, 500 views and 10 BBs: {1e3 * (time.perf_counter() - t0) / 20:.1f} ms (target < 50 ms)")
    background = phantom_background(experiment_phantom("A"), g, surface)
    t0 = time.perf_counter()
    predict_placement(g, xyz, d, surface=surface, background=background)
    t1 = time.perf_counter()
    for _ in range(20):
        predict_placement(g, xyz, d, surface=surface, background=background)
    print(
        f"with experiment A's background: {1e3 * (t1 - t0):.0f} ms the first time (a ray fan through the phantom per "
        f"BB and view), {1e3 * (time.perf_counter() - t1) / 20:.1f} ms for the same BBs again"
    )
    print(f"1-min load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
