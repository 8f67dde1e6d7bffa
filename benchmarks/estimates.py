"""Estimates against actual times: what orbitct says a job will take, and what it took.

Usage: .venv/bin/python benchmarks/estimates.py [--frames N] [--size PX] [--json FILE]
(recorded for the documentation with ``python benchmarks/record.py estimates``)
Scans the simulated bench and C-arm (their twins at real-time mechanics), simulates scans of experiments A and B and
calibrates them, reconstructs experiment A with FDK and PWLS at several grid sizes and plans BBs for experiments A and
B (``orbitct plan bbs``), and prints per job what it said it would take in all, the actual time and their ratio
(actual / estimate; the target is within 1.5 either way). Each says it at a different point: a reconstruction before
any large work (``recon.estimate``: rates measured on this machine when the process first needs them), a plan from one
placement scored before its search, a calibration once its first frames were read and searched, a step-mode scan once
its first three projections were taken (``acquire.pace``). A plan that looks for the fewest BBs says how long it takes
at most: its row is a bound. ``--json`` also writes the rows to a file.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

from machine_info import describe_machine

TARGET = 1.5  # an estimate within this factor of the actual time, either way


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120, help="projections of the simulated scan")
    ap.add_argument("--size", type=int, default=192, help="panel pixels per side")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows to this file")
    args = ap.parse_args()
    from orbitct.simulator.scan import simulate_scan
    from recon import reconstruct_scan

    print(f"machine: {describe_machine()}")
    rows: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        scan = Path(tmp) / "a.h5"
        simulate_scan("A", out=scan, n_frames=args.frames, detector_px=args.size)
        from recon.estimate import rates, reading_rate

        t = time.perf_counter()
        rates(), reading_rate()  # measured once per process (a service measures them once): not in the jobs' times
        print(f"rates measured in {time.perf_counter() - t:.2f} s (once per process)")
        cases = [
            ("FDK", {"algorithm": "fdk", "shape": [64, 96, 96], "voxel_mm": 1.0}),
            ("FDK", {"algorithm": "fdk", "shape": [128, 192, 192], "voxel_mm": 0.5}),
            ("PWLS", {"algorithm": "pwls", "shape": [32, 48, 48], "voxel_mm": 2.0, "iterations": 10}),
            ("PWLS", {"algorithm": "pwls", "shape": [64, 96, 96], "voxel_mm": 1.0, "iterations": 10}),
            ("PWLS", {"algorithm": "pwls", "shape": [96, 144, 144], "voxel_mm": 1.0, "iterations": 20}),
        ]
        for i, (job, options) in enumerate(cases):
            t = time.perf_counter()
            res = reconstruct_scan(scan, geometry="truth", name=f"r{i}", overwrite=True, fit="fov", **options)
            actual = time.perf_counter() - t
            estimated = float(res.params["estimated_s"])
            shape = "x".join(str(n) for n in options["shape"])  # type: ignore[attr-defined]
            what = f"{shape} voxels" + (f", {options['iterations']} iterations" if job == "PWLS" else "")
            rows.append(
                {
                    "job": job,
                    "case": f"{what}, {args.frames} views of {args.size}^2",
                    "estimated_s": estimated,
                    "actual_s": actual,
                    "ratio": actual / estimated if estimated > 0 else float("nan"),
                }
            )
        rows += calibration_rows(Path(tmp), scan, args.frames, args.size)
        rows += plan_rows(Path(tmp))
        rows += scan_rows(Path(tmp))
    print(f"\n| job | case | estimated s | actual s | actual / estimate | within {TARGET}x |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        ratio = float(r["ratio"])  # type: ignore[arg-type]
        ok = (ratio <= 1.0) if r.get("bound") else (1 / TARGET <= ratio <= TARGET)
        print(
            f"| {r['job']} | {r['case']} | {r['estimated_s']:.2f} | {r['actual_s']:.2f} | {ratio:.2f} | "
            f"{'yes' if ok else 'NO'} |"
        )
    if args.json is not None:
        args.json.write_text(json.dumps({"machine": describe_machine(), "rows": rows}))
        print(f"\nwrote {args.json}")


def _said(events: list[object]) -> float:
    """The ``expected_s`` a job said (its one ``duration`` progress event)."""
    return float(next(e.metrics["expected_s"] for e in events if e.stage == "duration"))  # type: ignore[attr-defined]


def calibration_rows(folder: Path, scan_a: Path, frames: int, size: int) -> list[dict[str, object]]:
    """Calibrations as ``orbitct calibrate`` runs them (the Python API it calls, kernels compiled beforehand): the time
    each says once its first frames were searched against its elapsed time (compiling left out of both)."""
    from calib import calibrate_scan
    from orbitct.simulator.scan import simulate_scan

    scan_b = folder / "b.h5"
    simulate_scan("B", out=scan_b, n_frames=250, detector_px=2 * size)
    calibrate_scan(scan_a, out=folder / "warm.h5")  # kernels compiled (or loaded) before timing
    rows: list[dict[str, object]] = []
    for case, scan in (
        (f"experiment A, {frames} views of {size}^2", scan_a),
        (f"experiment B, 250 views of {2 * size}^2", scan_b),
    ):
        events: list[object] = []
        res = calibrate_scan(scan, out=folder / f"cal-{scan.stem}.h5", progress=events.append)
        said = _said(events)
        rows.append(
            {
                "job": "calibration",
                "case": case,
                "estimated_s": said,
                "actual_s": res.elapsed_s,
                "ratio": res.elapsed_s / said,
            }
        )
    return rows


def scan_rows(folder: Path) -> list[dict[str, object]]:
    """Step-mode scans on the twins at real-time mechanics (``--sim``, as ``orbitct scan --sim`` runs them): the time
    each says, once its first three projections were taken, that its frames take in all, against their time."""
    from acquire.runner import ScanRequest, run_scan

    config = _HERE.parent / "config"
    cases = [
        ("bench sawtooth, 40 views", dict(config=config / "bench.yaml", orbit="sawtooth", frames=40)),
        (
            "bench sawtooth, 60 views, bench motion errors",
            dict(config=config / "bench.yaml", orbit="sawtooth", frames=60, errors="bench"),
        ),
        (
            "C-arm sawtooth, 80 views",
            dict(config=config / "carm-zeego.yaml", orbit="sawtooth", frames=80, orbit_params={"start_deg": -180.0}),
        ),
    ]
    rows: list[dict[str, object]] = []
    for i, (case, request) in enumerate(cases):
        events: list[object] = []
        res = run_scan(
            ScanRequest(out=folder / f"scan{i}.h5", sim=True, detector_size=192, **request), progress=events.append
        )  # type: ignore[arg-type]
        said = _said(events)
        rows.append(
            {
                "job": "scan",
                "case": f"{case} ({res.n_frames} frames)",
                "estimated_s": said,
                "actual_s": res.elapsed_s,
                "ratio": res.elapsed_s / said,
            }
        )
    return rows


def plan_rows(folder: Path) -> list[dict[str, object]]:
    """BB plans made as a user makes them (``orbitct plan bbs``): the time each says before its search against the
    time it took (both from the plan's ``time``, measured from when planning starts)."""
    rows: list[dict[str, object]] = []
    cases = [
        ("experiment A, its orbit, 8 BBs", ["-e", "A"], False),
        ("experiment B, 120 views, 6 BBs", ["-e", "B", "--frames", "120", "--bbs", "6"], False),
        (
            "experiment A, 90 views, fewest of up to 8 BBs for 0.3 px (at most)",
            ["-e", "A", "--frames", "90", "--target-px", "0.3", "--max-bbs", "8"],
            True,
        ),
    ]
    for i, (case, options, bound) in enumerate(cases):
        out = folder / f"plan{i}.json"
        command = [sys.executable, "-m", "orbitct_app.cli.main", "plan", "bbs", *options, "--out", str(out)]
        subprocess.run(command, check=True, capture_output=True, cwd=_HERE.parent)
        took = json.loads(out.read_text())["time"]
        rows.append(
            {
                "job": "BB planning",
                "case": case,
                "estimated_s": took["expected_s"],
                "actual_s": took["elapsed_s"],
                "ratio": took["elapsed_s"] / took["expected_s"],
                "bound": bound,
            }
        )
    return rows


if __name__ == "__main__":
    main()
