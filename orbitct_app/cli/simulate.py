"""``orbitct simulate`` (write a simulated scan) and ``orbitct inspect`` (summarise a scan file)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from orbitct_app.cli.progress import ProgressBar
from orbitct_app.cli.values import SEED, FiniteFloat

if TYPE_CHECKING:
    from orbitct.phantoms.phantom import Phantom


@click.command()
@click.option(
    "--experiment",
    "-e",
    type=click.Choice(["A", "B", "C"], case_sensitive=False),
    required=True,
    help="phantom of the paper's experiment A (bench), B (Cho cylinder + wire) or C (torso + screws)",
)
@click.option(
    "--orbit",
    "orbit_name",
    default=None,
    metavar="NAME",
    help="orbit kind (default per experiment: A sawtooth, B dcarc, C multiarc preset pheno)",
)
@click.option("--param", "-p", "params", multiple=True, metavar="KEY=VALUE", help="orbit parameter (repeatable)")
@click.option("--frames", type=click.IntRange(min=2), default=None, help="projection frames (default: the orbit's)")
@click.option(
    "--detector-size",
    type=click.IntRange(min=8, max=4096),
    default=768,
    show_default=True,
    help="detector rows = cols (pixels); the 427 mm panel keeps its size",
)
@click.option(
    "--pitch-mm",
    type=FiniteFloat(min=0, min_open=True),
    default=None,
    help="pixel pitch (default 427 mm / detector size)",
)
@click.option(
    "--errors",
    type=click.Choice(["bench", "none"]),
    default="bench",
    show_default=True,
    help="motion errors added to the orbit",
)
@click.option(
    "--detector",
    type=click.Choice(["clean", "realistic"]),
    default="clean",
    show_default=True,
    help="the panel's images: clean, or realistic (wider blur, scatter, lag, dead pixels and columns)",
)
@click.option(
    "--beam",
    type=click.Choice(["mono", "polychromatic"]),
    default="mono",
    show_default=True,
    help="the tube's beam: one energy, or a 90 kV spectrum through 3 mm Al + 0.1 mm Cu (beam hardening)",
)
@click.option(
    "--clutter",
    type=click.Choice(["none", "anatomy"]),
    default="none",
    show_default=True,
    help="anatomy: add a patient's fat, vessels, ribs, a guide wire and ECG leads to experiment C's torso",
)
@click.option("--seed", type=SEED, default=0, show_default=True, help="phantom layout, errors and noise")
@click.option("--darks", type=click.IntRange(min=0), default=10, show_default=True, help="dark frames")
@click.option("--flats", type=click.IntRange(min=0), default=10, show_default=True, help="flat frames")
@click.option("--out", "-o", type=click.Path(dir_okay=False, path_type=Path), required=True, help="scan file to write")
@click.option("--overwrite", is_flag=True, help="replace --out if it exists")
@click.option(
    "--bbs-from",
    "bbs_from",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="place the BBs as in this plan (orbitct plan bbs --out PLAN.json)",
)
def simulate(
    experiment: str,
    orbit_name: str | None,
    params: tuple[str, ...],
    frames: int | None,
    detector_size: int,
    pitch_mm: float | None,
    errors: str,
    detector: str,
    beam: str,
    clutter: str,
    seed: int,
    darks: int,
    flats: int,
    out: Path,
    overwrite: bool,
    bbs_from: Path | None,
) -> None:
    """Simulate a scan of an experiment phantom and write it as a scan file."""
    from orbitct.orbits import OrbitError
    from orbitct.simulator import resolve_orbit, simulate_scan

    if out.exists() and not overwrite:
        raise click.BadParameter(f"{out} already exists (add --overwrite to replace it)", param_hint="--out")
    orbit_params = parse_params(params)
    if "n_frames" in orbit_params:  # -p n_frames=N is --frames N
        said = orbit_params.pop("n_frames")
        if frames is not None and said != frames:
            raise click.UsageError(f"--frames {frames} and -p n_frames={said} disagree; give the number of frames once")
        if not isinstance(said, int) or isinstance(said, bool):
            raise click.UsageError(f"-p n_frames={said!r} is not a whole number of frames")
        frames = said
    try:
        orbit = resolve_orbit(experiment, orbit_name, frames, **orbit_params)
    except OrbitError as exc:
        raise click.UsageError(str(exc)) from None
    if clutter != "none" and experiment.upper() != "C":
        raise click.BadParameter(f"{clutter} clutter is made for experiment C's torso", param_hint="--clutter")
    phantom: str | Phantom = experiment.upper()
    if bbs_from is not None:
        phantom = _planned_phantom(experiment.upper(), seed, bbs_from, clutter)
    elif clutter != "none":
        from orbitct.phantoms.experiments import experiment_phantom

        phantom = experiment_phantom(experiment, seed, clutter=clutter)
    with ProgressBar() as bar:
        res = simulate_scan(
            phantom,
            orbit,
            out=out,
            detector_px=detector_size,
            pitch_mm=pitch_mm,
            errors=errors,
            detector=detector,
            beam=beam,
            seed=seed,
            n_dark=darks,
            n_flat=flats,
            overwrite=overwrite,
            progress=bar,
        )
    click.echo(
        f"wrote {res.path}: {res.n_projections} projections + {darks} darks + {flats} flats, "
        f"orbit {res.orbit.name}, {res.phantom.n_markers} markers, {res.elapsed_s:.1f} s "
        f"({res.frames_per_s:.1f} frames/s)"
    )


def _planned_phantom(experiment: str, seed: int, plan: Path, clutter: str = "none") -> Phantom:
    """The experiment's object with the BBs of a plan (JSON of ``orbitct plan bbs``)."""
    from orbitct.phantoms.experiments import experiment_phantom
    from orbitct_app.bbplan import BBPlanError, read_bb_plan

    try:
        planned_for, xyz, diameter = read_bb_plan(plan)
    except BBPlanError as exc:
        raise click.BadParameter(str(exc), param_hint="--bbs-from") from None
    if planned_for not in (None, experiment):
        raise click.BadParameter(
            f"{plan} was planned for experiment {planned_for}, not {experiment}", param_hint="--bbs-from"
        )
    return experiment_phantom(experiment, seed, clutter=clutter).with_markers(xyz, diameter)


def _value(text: str) -> object:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_params(items: tuple[str, ...] | list[str]) -> dict[str, object]:
    """``KEY=VALUE`` strings to a dict; values are JSON when they parse (numbers, lists), else strings."""
    out: dict[str, object] = {}
    for item in items:
        key, sep, val = item.partition("=")
        if not sep or not key.strip():
            raise click.BadParameter(f"expected KEY=VALUE, got {item!r}", param_hint="--param")
        out[key.strip()] = _value(val.strip())
    return out


@click.command()
@click.argument("scan", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="print the summary as JSON")
def inspect(scan: Path, as_json: bool) -> None:
    """Summarise a scan file: frames by kind, geometry, markers, status, orbit; and whether it can be used.

    Exit status 0 when orbitct calibrate or reconstruct can use the file, 1 (with the reasons) when neither can."""
    from orbitct.scanfile import ScanFile, ScanFileError, scan_summary
    from orbitct.scanfile.reader import HDF5_ERRORS, damaged

    try:
        with ScanFile(scan) as f:
            summary = scan_summary(f)
            unusable = f.unusable_because()
    except ScanFileError as exc:
        raise click.ClickException(str(exc)) from None
    except HDF5_ERRORS as exc:  # damage past what opening the file checks (a result's group, an attribute's heap)
        raise click.ClickException(str(damaged(scan, exc))) from None
    summary["usable"], summary["unusable_because"] = not unusable, unusable
    if as_json:
        click.echo(json.dumps(summary, indent=2, default=str))
    else:
        _print_summary(scan, summary)
    if unusable:  # a file the computations would refuse is never reported as fine
        raise click.ClickException(f"{scan}: not usable by orbitct calibrate or reconstruct: {'; '.join(unusable)}")


def _print_summary(scan: Path, summary: dict[str, Any]) -> None:
    """The summary for a person."""
    click.echo(f"{scan}")
    click.echo(
        f"  status      {summary['status']}" + (f" ({summary['status_reason']})" if summary["status_reason"] else "")
    )
    if summary.get("frames_file"):
        click.echo(f"  pixels      read from {summary['frames_file']} (keep the two files together)")
    d = summary["detector"]
    click.echo(f"  detector    {d['rows']} x {d['cols']} px @ {d['pitch_mm'][0]:.4g} x {d['pitch_mm'][1]:.4g} mm")
    click.echo(
        "  frames      "
        + ", ".join(f"{v} {k}" for k, v in summary["frames_by_kind"].items() if v)
        + f" ({summary['n_frames']} total, {summary['dtype']})"
    )
    if summary["frames_without_pixels"]:
        click.echo(
            f"  warning     {summary['frames_without_pixels']} more frame(s) at the end have no pixels in the file "
            "(the disk filled up while they were written) and are left out; orbitct scan repair trims them"
        )
    for axis, off in summary["taken_off_command"].items():
        unit = f" {off['unit']}" if off["unit"] else ""
        click.echo(
            f"  warning     {off['frames']} projection(s) read back further from their command than a step of "
            f"{axis} ({off['step']:.3g}{unit}), up to {off['max']:.3g}{unit}: their nominal geometry is not where "
            "they were taken; calibrate from the BBs, or scan again"
        )
    if summary["duration_s"] is not None:
        click.echo(f"  duration    {summary['duration_s']:.1f} s")
    click.echo(f"  orbit       {summary['orbit']['name'] or '-'} {json.dumps(summary['orbit']['params'])}")
    if "rotation_deg" in summary["orbit"]:
        o = summary["orbit"]
        click.echo(
            f"              nominal source rotation {o['rotation_deg'][0]:.1f}..{o['rotation_deg'][1]:.1f} deg, "
            f"tilt {o['tilt_deg'][0]:.1f}..{o['tilt_deg'][1]:.1f} deg"
        )
    cal = summary["calibration"]
    notes = {
        "calibrated": f"RPE mean {cal['rpe_mean_mm']:.3f} mm, median {cal['rpe_median_mm']:.3f} mm"
        if cal.get("rpe_mean_mm") is not None and cal.get("rpe_median_mm") is not None
        else ""
    }
    click.echo(
        "  geometry    " + ", ".join(g + (f" ({notes[g]})" if notes.get(g) else "") for g in summary["geometries"])
        if summary["geometries"]
        else "  geometry    none"
    )
    if summary["live_calibration"]:
        click.echo(f"  live        calibration during the scan: {summary['live_calibration']['outcome']}")
    m = summary["markers"]
    dia = f"{m['diameter_mm']} mm" if m["diameter_mm"] is not None else "diameter unknown"

    def count(n: int) -> str:
        return f"{n} markers" if n else "no"

    click.echo(
        f"  markers     {dia}; detected uv: {count(m['detected'])}; estimated xyz: {count(m['estimated'])}; "
        f"truth: {count(m['truth'])}"
    )
    if summary["phantom"]:
        click.echo(f"  phantom     {summary['phantom']}")
    if summary["recon"]:
        click.echo(f"  recon       {', '.join(summary['recon'])}")
    for text in summary["ignored"]:
        click.echo(f"  warning     {text}")
    for text in summary["damaged"]:
        click.echo(f"  warning     damaged: {text}; calibration and reconstruction do not read it")
