"""``orbitct plan bbs``: where to tape the BBs for an orbit, with the calibration accuracy each view can expect."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click
import numpy as np


@click.group()
def plan() -> None:
    """Plan an acquisition before it runs."""


@plan.command("bbs")
@click.option("--experiment", "-e", type=click.Choice(["A", "B", "C"], case_sensitive=False), required=True,
              help="The object (its surface, metal and BB size) and its default orbit.")
@click.option("--orbit", "orbit_name", default=None, metavar="NAME", help="orbit kind (default: the experiment's)")
@click.option("--frames", type=click.IntRange(min=2), default=None, help="projections (default: the orbit's)")
@click.option("--bbs", "n_bbs", type=click.IntRange(min=4, max=40), default=8, show_default=True, help="BBs to place")
@click.option("--detector-size", type=click.IntRange(min=8, max=4096), default=768, show_default=True)
@click.option("--noise-px", type=click.FloatRange(min=0.0, min_open=True), default=0.1, show_default=True,
              help="centroid noise of the BB detection (a calibration reports it as centroid_noise_px)")
@click.option("--seed", type=int, default=0, show_default=True, help="the search's random start")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="the plan (JSON); a picture is written beside it (.png)")
def bbs(experiment: str, orbit_name: str | None, frames: int | None, n_bbs: int, detector_size: int, noise_px: float,
        seed: int, out: Path) -> None:
    """Search BB positions on the object's surface that minimise the predicted calibration error of the orbit's
    views (the worst views weighted), and compare with the experiment's own placement."""
    from calib.plan import (
        Surface,
        metal_of,
        placement_score,
        plan_placement,
        predict_placement,
    )
    from orbitct.orbits import OrbitError
    from orbitct.phantoms.experiments import BB_SURFACES, experiment_phantom
    from orbitct.simulator import resolve_orbit
    from orbitct.simulator.bench import SimulatedBench

    key = experiment.upper()
    try:
        orbit = resolve_orbit(key, orbit_name, frames)
    except OrbitError as exc:
        raise click.UsageError(str(exc)) from None
    phantom = experiment_phantom(key)
    d = float(phantom.marker_diameter_mm or 3.0)
    geometry = SimulatedBench.with_panel(detector_size).nominal_geometry(orbit)
    metal = metal_of(phantom)
    surface = Surface(*BB_SURFACES[key])
    try:
        placed = plan_placement(geometry, surface, n_bbs, d, noise_px=noise_px, metal=metal, seed=seed)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    own = predict_placement(geometry, phantom.markers_xyz, d, noise_px=noise_px, metal=metal)
    pred = placed.prediction
    body: dict[str, Any] = {
        "experiment": key, "orbit": orbit.name, "views": int(geometry.n_views), "detector_px": detector_size,
        "bb_diameter_mm": d, "noise_px": noise_px, "surface": vars(surface),
        "bbs": [{"number": k + 1, "xyz_mm": [round(float(v), 2) for v in placed.xyz[k]],
                 "angle_deg": round(float(np.degrees(placed.angle_rad[k])) % 360.0, 1),
                 "height_mm": round(float(placed.z_mm[k]), 1)} for k in range(n_bbs)],
        "predicted": pred.summary(), "score": placed.score,
        "experiment_placement": {"bbs": int(phantom.n_markers), "predicted": own.summary(), "score": placement_score(own)},
        "per_view": {"n_bbs": pred.n_bbs.tolist(),
                     "predicted_px": [None if not np.isfinite(v) else round(float(v), 4) for v in pred.predicted_px]},
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(body, indent=1))
    picture = out.with_suffix(".png")
    _picture(picture, placed, own, surface, key)
    click.echo(f"{key}, orbit {orbit.name} ({geometry.n_views} views), {n_bbs} BBs of {d:g} mm, centroid noise {noise_px:g} px")
    click.echo("  BB  angle deg  height mm   x mm    y mm    z mm")
    for b in body["bbs"]:
        x, y, z = b["xyz_mm"]
        click.echo(f"  {b['number']:>2}  {b['angle_deg']:9.1f}  {b['height_mm']:9.1f}  {x:6.1f}  {y:6.1f}  {z:6.1f}")
    for name, s, n in (("planned", pred.summary(), n_bbs), ("the experiment's own", own.summary(), phantom.n_markers)):
        click.echo(f"  {name} ({n} BBs): predicted error median {s['predicted_px_median']:.3f} px, worst "
                   f"{s['predicted_px_max']:.3f} px; usable BBs per view at least {s['bbs_min']}, median {s['bbs_median']:g}; "
                   f"{s['under_determined']} view(s) under-determined")
    if pred.under_determined.size:
        click.echo(f"warning: {pred.under_determined.size} view(s) see fewer than 4 usable BBs (first: "
                   f"{pred.under_determined[:8].tolist()}); more BBs, or another orbit", err=True)
    click.echo(f"wrote {out} and {picture}")


def _picture(path: Path, placed: Any, own: Any, surface: Any, experiment: str) -> None:
    """The BBs on the unrolled surface with their numbers; BBs per view and the predicted error along the orbit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax0.scatter(np.degrees(placed.angle_rad) % 360.0, placed.z_mm, s=60, c="tab:red")
    for k, (a, z) in enumerate(zip(np.degrees(placed.angle_rad) % 360.0, placed.z_mm, strict=True)):
        ax0.annotate(str(k + 1), (a, z), textcoords="offset points", xytext=(5, 5))
    ax0.set(xlim=(0, 360), ylim=(surface.z_min_mm - 5, surface.z_max_mm + 5), xlabel="angle on the object (deg, from +x)",
            ylabel="height (mm)", title=f"experiment {experiment}: where to tape the BBs")
    ax0.grid(alpha=0.3)
    views = np.arange(placed.prediction.n_bbs.size)
    ax1.plot(views, placed.prediction.predicted_px, label="planned: predicted error (px)")
    ax1.plot(views, own.predicted_px, label="experiment's placement", alpha=0.7)
    ax1.set(xlabel="view", ylabel="predicted error (px)", title="calibration accuracy along the orbit")
    ax1b = ax1.twinx()
    ax1b.step(views, placed.prediction.n_bbs, color="grey", alpha=0.4, where="mid")
    ax1b.set_ylabel("usable BBs (planned)")
    ax1.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
