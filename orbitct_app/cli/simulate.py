"""``orbitct simulate`` (write a simulated scan) and ``orbitct inspect`` (summarise a scan file)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import click
import numpy as np

from orbitct_app.cli.progress import ProgressBar

if TYPE_CHECKING:
    from orbitct.scanfile import ScanFile


@click.command()
@click.option("--experiment", "-e", type=click.Choice(["A", "B", "C"], case_sensitive=False), required=True,
              help="phantom of the paper's experiment A (bench), B (Cho cylinder + wire) or C (torso + screws)")
@click.option("--orbit", "orbit_name", default=None, metavar="NAME",
              help="orbit kind (default per experiment: A sawtooth, B dcarc, C multiarc preset pheno)")
@click.option("--param", "-p", "params", multiple=True, metavar="KEY=VALUE", help="orbit parameter (repeatable)")
@click.option("--frames", type=click.IntRange(min=2), default=None, help="projection frames (default: the orbit's)")
@click.option("--detector-size", type=click.IntRange(min=8, max=4096), default=768, show_default=True,
              help="detector rows = cols (pixels); the 427 mm panel keeps its size")
@click.option("--pitch-mm", type=click.FloatRange(min=0, min_open=True), default=None,
              help="pixel pitch (default 427 mm / detector size)")
@click.option("--errors", type=click.Choice(["bench", "none"]), default="bench", show_default=True,
              help="motion errors added to the orbit")
@click.option("--seed", type=int, default=0, show_default=True, help="phantom layout, errors and noise")
@click.option("--darks", type=click.IntRange(min=0), default=10, show_default=True, help="dark frames")
@click.option("--flats", type=click.IntRange(min=0), default=10, show_default=True, help="flat frames")
@click.option("--out", "-o", type=click.Path(dir_okay=False, path_type=Path), required=True, help="scan file to write")
@click.option("--overwrite", is_flag=True, help="replace --out if it exists")
def simulate(experiment: str, orbit_name: str | None, params: tuple[str, ...], frames: int | None, detector_size: int,
             pitch_mm: float | None, errors: str, seed: int, darks: int, flats: int, out: Path, overwrite: bool) -> None:
    """Simulate a scan of an experiment phantom and write it as a scan file."""
    from orbitct.orbits import OrbitError
    from orbitct.simulator import resolve_orbit, simulate_scan

    if out.exists() and not overwrite:
        raise click.BadParameter(f"{out} already exists (add --overwrite to replace it)", param_hint="--out")
    try:
        orbit = resolve_orbit(experiment, orbit_name, frames, **parse_params(params))
    except OrbitError as exc:
        raise click.UsageError(str(exc)) from None
    with ProgressBar() as bar:
        res = simulate_scan(experiment.upper(), orbit, out=out, detector_px=detector_size, pitch_mm=pitch_mm,
                            errors=errors, seed=seed, n_dark=darks, n_flat=flats, overwrite=overwrite, progress=bar)
    click.echo(f"wrote {res.path}: {res.n_projections} projections + {darks} darks + {flats} flats, "
               f"orbit {res.orbit.name}, {res.phantom.n_markers} markers, {res.elapsed_s:.1f} s "
               f"({res.frames_per_s:.1f} frames/s)")


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
    """Summarise a scan file: frames by kind, geometry, markers, status, orbit."""
    from orbitct.scanfile import ScanFile, ScanFileError

    try:
        with ScanFile(scan) as f:
            summary = scan_summary(f)
    except ScanFileError as exc:
        raise click.ClickException(str(exc)) from None
    if as_json:
        click.echo(json.dumps(summary, indent=2, default=str))
        return
    click.echo(f"{scan}")
    click.echo(f"  status      {summary['status']}" + (f" ({summary['status_reason']})" if summary["status_reason"] else ""))
    d = summary["detector"]
    click.echo(f"  detector    {d['rows']} x {d['cols']} px @ {d['pitch_mm'][0]:.4g} x {d['pitch_mm'][1]:.4g} mm")
    click.echo("  frames      " + ", ".join(f"{v} {k}" for k, v in summary["frames"].items() if v) +
               f" ({summary['n_frames']} total, {summary['dtype']})")
    if summary["duration_s"] is not None:
        click.echo(f"  duration    {summary['duration_s']:.1f} s")
    click.echo(f"  orbit       {summary['orbit']['name'] or '-'} {json.dumps(summary['orbit']['params'])}")
    if "rotation_deg" in summary["orbit"]:
        o = summary["orbit"]
        click.echo(f"              nominal source rotation {o['rotation_deg'][0]:.1f}..{o['rotation_deg'][1]:.1f} deg, "
                   f"tilt {o['tilt_deg'][0]:.1f}..{o['tilt_deg'][1]:.1f} deg")
    click.echo("  geometry    " + ", ".join(f"{k}{' (' + v + ')' if v else ''}" for k, v in summary["geometry"].items())
               if summary["geometry"] else "  geometry    none")
    m = summary["markers"]
    dia = f"{m['diameter_mm']} mm" if m["diameter_mm"] is not None else "diameter unknown"
    click.echo(f"  markers     {dia}; detected uv: {m['uv'] or 'no'}; estimated xyz: {m['xyz'] or 'no'}; "
               f"truth: {m['truth'] or 'no'}")
    if summary["phantom"]:
        click.echo(f"  phantom     {summary['phantom']}")
    if summary["recon"]:
        click.echo(f"  recon       {', '.join(summary['recon'])}")


def scan_summary(f: "ScanFile") -> dict[str, object]:
    """JSON-able summary of an open :class:`orbitct.scanfile.ScanFile`."""
    det = f.panel
    geometry: dict[str, str] = {}
    for name in ("nominal", "calibrated", "truth"):
        if f.has_geometry(name):
            extra = ""
            if name == "calibrated":
                a = f.h5["geometry/calibrated"].attrs
                if "rpe_mean_mm" in a:
                    extra = f"RPE mean {float(a['rpe_mean_mm']):.3f} mm, median {float(a['rpe_median_mm']):.3f} mm"
            geometry[name] = extra
    mk = f.markers()
    truth = f.truth_markers_xyz()
    name, params = f.orbit
    orbit: dict[str, object] = {"name": name, "params": params}
    idx = f.projection_indices
    if f.has_geometry("nominal") and idx.size:
        S = f.geometry("nominal").S[idx]
        d = S / np.linalg.norm(S, axis=1, keepdims=True)
        rot = np.degrees(np.unwrap(np.arctan2(d[:, 0], -d[:, 1])))
        tilt = np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))
        orbit["rotation_deg"] = [float(rot.min()), float(rot.max())]
        orbit["tilt_deg"] = [float(tilt.min()), float(tilt.max())]
    ph = f.phantom
    return {
        "status": f.status,
        "status_reason": f.status_reason,
        "detector": {"rows": det.rows, "cols": det.cols, "pitch_mm": list(det.pitch_mm)},
        "n_frames": f.n_frames,
        "dtype": str(f.frames.dtype),
        "frames": f.count_by_kind(),
        "duration_s": float(np.nanmax(f.time_s)) if f.n_frames and np.isfinite(f.time_s).any() else None,
        "orbit": orbit,
        "geometry": geometry,
        "markers": {
            "diameter_mm": f.marker_diameter_mm,
            "uv": f"{mk['uv'].shape[1]} markers" if "uv" in mk else "",
            "xyz": f"{mk['xyz'].shape[0]} markers" if "xyz" in mk else "",
            "truth": f"{truth.shape[0]} markers" if truth is not None else "",
        },
        "phantom": (f"{ph.get('name', '')}: {len(ph.get('primitives', []))} primitives" if ph else ""),
        "recon": f.recon_names(),
    }
