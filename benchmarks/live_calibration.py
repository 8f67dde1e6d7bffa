"""Benchmark: calibrating during the scan, side by side with the offline calibration of the same file.

The same scan on the twins runs twice, without and with live calibration (``orbitct scan --calibrate live``):
frame rate of each, how long after the last frame the calibrated geometry is in the file (and how much of that
is the worker catching up and how much the final solve), then ``orbitct calibrate`` of the live scan's file;
accuracy of both against the twins' truth (RMS px over field-of-view points after similarity alignment).

    python benchmarks/live_calibration.py                          # 256 px, 250 frames
    python benchmarks/live_calibration.py --size 768 --frames 500  # the issue's target size
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

from machine_info import describe_machine


def _scan(out: Path, size: int, frames: int, live: bool) -> dict[str, Any]:
    """``orbitct scan`` on the twins (a fresh process, as an operator runs it); what it printed, as numbers."""
    cmd = [
        sys.executable,
        "-m",
        "orbitct_app.cli.main",
        "scan",
        "--config",
        str(_HERE.parent / "config" / "bench.yaml"),
        "--orbit",
        "sawtooth",
        "--frames",
        str(frames),
        "--errors",
        "bench",
        "--sim",
        "--detector-size",
        str(size),
        "--out",
        str(out),
        "--overwrite",
    ] + (["--calibrate", "live"] if live else [])
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=_HERE.parent)
    text = run.stdout
    done = re.search(r"complete: (\d+)/\d+ frames(?: \([^)]*\))? in ([\d.]+) s", text)
    if done is None:
        raise SystemExit(f"scan failed (exit {run.returncode}):\n{text}\n{run.stderr[-2000:]}")
    out_: dict[str, Any] = {"frames": float(done.group(1)), "elapsed_s": float(done.group(2))}
    m = re.search(
        r"geometry written ([\d.]+) s after the last frame \(catching up ([\d.]+) s, final solve ([\d.]+) s\); "
        r"(\d+) warning\(s\) during the scan( \(([^)]*)\))?",
        text,
    )
    if live and m is not None:
        out_.update(
            after_s=float(m.group(1)),
            catch_up_s=float(m.group(2)),
            solve_s=float(m.group(3)),
            warnings=float(m.group(4)),
        )
        out_["warning_kinds"] = m.group(6) or "none"
        w = re.search(
            r"(\d+) sliding bundle adjustment\(s\) in the worker \(([\d.]+) s\); live poses for (\d+) of", text
        )
        if w is not None:
            out_.update(windows=float(w.group(1)), window_s=float(w.group(2)), posed=float(w.group(3)))
    out_["passed"] = float("QUALITY CHECK FAILED" not in run.stderr)
    return out_


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="detector pixels per side")
    ap.add_argument("--frames", type=int, default=250, help="projections")
    args = ap.parse_args()
    import calib
    from calib.evaluate import similarity_aligned_error_px
    from orbitct.scanfile import ScanFile

    print(describe_machine())
    print(
        f"{args.size} px, {args.frames} projections, sawtooth, bench errors, twins in this process; "
        f"1-min load at start {os.getloadavg()[0]:.2f}\n"
    )
    with tempfile.TemporaryDirectory() as tmp:
        plain = _scan(Path(tmp) / "plain.h5", args.size, args.frames, live=False)
        live_file = Path(tmp) / "live.h5"
        live = _scan(live_file, args.size, args.frames, live=True)
        if "after_s" not in live:
            raise SystemExit("the live calibration did not report its geometry")
        rate_plain = plain["frames"] / plain["elapsed_s"]
        rate_live = live["frames"] / live["elapsed_s"]
        with ScanFile(live_file) as sf:
            proj = sf.projection_indices
            truth = sf.geometry("truth")[proj]
            live_geometry = sf.geometry("calibrated")[proj]
        t = time.perf_counter()
        offline = calib.calibrate_scan(live_file, out=Path(tmp) / "offline.h5")
        offline_wall = time.perf_counter() - t
        live_err, _ = similarity_aligned_error_px(live_geometry, truth)
        off_err, _ = similarity_aligned_error_px(offline.geometry[proj], truth)
        print(
            "| run | frames/s | geometry after last frame s | of which catching up s | final solve s | err px | verdict |"
        )
        print("|---|---|---|---|---|---|---|")
        print(f"| scan only | {rate_plain:.2f} | - | - | - | - | - |")
        print(
            f"| scan + live calibration | {rate_live:.2f} ({100 * (rate_live / rate_plain - 1):+.1f} %) | "
            f"{live['after_s']:.2f} | {live['catch_up_s']:.2f} | {live['solve_s']:.2f} | {live_err:.3f} | "
            f"{'passed' if live['passed'] else 'failed'} |"
        )
        print(
            f"| offline orbitct calibrate of the same file | - | {offline_wall:.2f} (after the scan, wall) | - | "
            f"{offline.elapsed_s:.2f} | {off_err:.3f} ({100 * (live_err / off_err - 1):+.1f} % live vs offline) | "
            f"{'passed' if offline.quality is not None and offline.quality.passed else 'failed'} |"
        )
        print(f"\nlive warnings during the scan: {int(live['warnings'])} ({live.get('warning_kinds', '?')})")
        if "windows" in live:
            print(
                f"sliding bundle adjustments in the worker: {int(live['windows'])} ({live['window_s']:.2f} s in all); "
                f"frames posed live: {int(live['posed'])} of {args.frames}"
            )
    print(f"1-min load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
