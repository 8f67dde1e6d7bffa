"""Acquisition benchmark: a sawtooth scan on the in-process twins, timed per part, and its X-ray dose time.

Reports the whole scan time and, per frame, the time spent in detector acquisition
(X-ray exposure, rendering on the twin, frame transfer), in commanded motion and
settling (twin mechanics, scaled by --time-scale), and the rest: what the executor
and the recorder add (read-backs, bookkeeping, HDF5 write and flush, progress).

Then the high-voltage policy: a shorter step scan twice, once as orbitct runs it (high voltage
off whenever the next exposure is further away than the generator's preparation time) and
once with high voltage held on between exposures (as before); reports, in bench seconds, the
time with high voltage on while nothing exposes and the scan time each costs.

    .venv/bin/python benchmarks/acquire.py                       # 500 frames at 768 x 768 (targets)
    .venv/bin/python benchmarks/acquire.py --frames 100 --size 256   # quicker
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine_info import describe_machine as machine

from acquire.config import BenchConfig, load_config
from acquire.errors import AcquireError
from acquire.rigs.bench import open_bench
from acquire.runner import ScanRequest, ScanRunner, run_scan
from devices.sim import twin_of
from orbitct.scanfile import ScanFile

TARGET_OVERHEAD_MS = 10.0
TARGET_TOTAL_S = 60.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=500, help="projections (default 500)")
    ap.add_argument("--size", type=int, default=768, help="detector pixels, square (default 768)")
    ap.add_argument("--mode", choices=["step", "continuous"], default="step")
    ap.add_argument(
        "--time-scale",
        type=float,
        default=50.0,
        help="twins move this many times faster than a real bench (default 50: mechanics out of the way)",
    )
    ap.add_argument(
        "--tilt-deg", type=float, default=8.0, help="sawtooth tilt amplitude (the hexapod twin allows ~8 with errors)"
    )
    ap.add_argument("--frame-rate", type=float, default=None, help="continuous mode: frames per second")
    ap.add_argument(
        "--overlap-readout",
        action="store_true",
        help="step mode: move to the next frame while the panel reads out (config motion.overlap_readout)",
    )
    ap.add_argument("--out", type=Path, default=None, help="keep the scan file here (default: a temporary folder)")
    ap.add_argument(
        "--dose-frames", type=int, default=100, help="projections of each high-voltage policy scan (0: skip)"
    )
    ap.add_argument(
        "--dose-time-scale", type=float, default=10.0, help="twin speed-up of the high-voltage policy scans"
    )
    args = ap.parse_args()

    cfg = load_config(ROOT / "config" / "bench.yaml")
    assert isinstance(cfg, BenchConfig)
    cfg = cfg.with_detector_size(args.size)
    cfg = cfg.model_copy(
        update={
            "sim": cfg.sim.model_copy(update={"time_scale": args.time_scale}),
            "motion": cfg.motion.model_copy(update={"overlap_readout": args.overlap_readout}),
        }
    )
    tmp = tempfile.TemporaryDirectory()
    out = args.out or Path(tmp.name) / "bench.h5"
    req = ScanRequest(
        config=cfg,
        out=out,
        orbit="sawtooth",
        frames=args.frames,
        orbit_params={"amplitude_deg": args.tilt_deg},
        errors="bench",
        seed=0,
        mode=args.mode,
        sim=True,
        frame_rate_hz=args.frame_rate,
        overwrite=True,
    )
    t0 = time.perf_counter()
    try:
        res = run_scan(req)
    except AcquireError as exc:
        sys.exit(f"scan refused: {exc}")
    wall = time.perf_counter() - t0
    if res.status != "complete":
        sys.exit(f"scan {res.status}: {res.reason}")
    with ScanFile(out) as sf:
        n = sf.n_frames
        size_mb = out.stat().st_size / 1e6
    t = res.timing
    per = {k: 1000.0 * v / n for k, v in t.items()}
    rows = [
        ("frames (projections + darks/flats)", f"{n}", ""),
        ("detector", f"{args.size} x {args.size} uint16", ""),
        (
            "mode / twin time scale",
            f"{args.mode}{' + overlapped readout' if args.overlap_readout else ''} / {args.time_scale:g}x",
            "",
        ),
        ("whole run incl. connect + pre-flight (s)", f"{wall:.1f}", f"< {TARGET_TOTAL_S:g}"),
        ("frame loop (s)", f"{t['run_s']:.1f}", ""),
        ("acquisition: exposure + render + transfer (ms/frame)", f"{per['acquire_s']:.1f}", ""),
        ("motion + settle, twin mechanics (ms/frame)", f"{per['motion_s']:.1f}", ""),
        ("executor + recorder overhead (ms/frame)", f"{per['overhead_s']:.2f}", f"< {TARGET_OVERHEAD_MS:g}"),
        ("  of which axis read-backs, 7 axes (ms/frame)", f"{per['readback_s']:.2f}", ""),
        ("  of which recorder: HDF5 write + flush (ms/frame)", f"{per['record_s']:.2f}", ""),
        ("frames per second", f"{n / t['run_s']:.1f}", ""),
        ("scan file size (MB)", f"{size_mb:.0f}", ""),
    ]
    print(f"acquisition benchmark on {machine()}")
    w = max(len(r[0]) for r in rows)
    for name, value, target in rows:
        print(f"  {name:<{w}}  {value:>22}  {target}")
    ok = per["overhead_s"] < TARGET_OVERHEAD_MS and wall < TARGET_TOTAL_S
    print("targets met" if ok else "targets NOT met")
    if args.dose_frames:
        dose_policy(cfg, args.dose_frames, args.dose_time_scale, args.tilt_deg, Path(tmp.name))


def dose_policy(cfg: BenchConfig, frames: int, time_scale: float, tilt_deg: float, folder: Path) -> None:
    """The same step scan with high voltage off between exposures (orbitct) and held on (before); bench seconds."""
    cfg = cfg.with_detector_size(64).model_copy(update={"sim": cfg.sim.model_copy(update={"time_scale": time_scale})})

    async def scan(hold_on: bool) -> tuple[float, float, float, int]:
        req = ScanRequest(
            config=cfg,
            out=folder / f"dose-{hold_on}.h5",
            orbit="sawtooth",
            frames=frames,
            orbit_params={"amplitude_deg": tilt_deg},
            sim=True,
            overwrite=True,
        )
        async with open_bench(cfg, sim=True) as rig:
            if hold_on:  # the old behaviour: prepared once, held on until the scan ends
                rig.xray.hold_s, rig.prep_s = None, float("inf")
            twin = twin_of(rig.xray)
            hv0, ex0 = twin.dose_seconds()
            res = await ScanRunner(req, rig=rig).run()
            hv, ex = twin.dose_seconds()
        return res.timing["run_s"] * time_scale, (hv - hv0) * time_scale, (ex - ex0) * time_scale, res.n_frames

    rows = {
        name: asyncio.run(scan(hold))
        for name, hold in (("off between exposures (orbitct)", False), ("held on between exposures", True))
    }
    print(
        f"high voltage policy: {frames} projections at 64 x 64, twins at {time_scale:g}x, "
        f"preparation time {cfg.exposure.prep_ms:g} ms (bench seconds)"
    )
    print(f"  {'policy':<34} {'scan s':>8} {'HV on s':>8} {'exposing s':>11} {'HV on, not exposing s':>22}")
    for name, (run_s, hv, ex, _n) in rows.items():
        print(f"  {name:<34} {run_s:8.1f} {hv:8.2f} {ex:11.2f} {hv - ex:22.2f}")
    (a_run, a_hv, a_ex, _), (b_run, b_hv, b_ex, _) = rows.values()
    print(
        f"  dose-free time: {(b_hv - b_ex) - (a_hv - a_ex):.1f} s less high voltage without exposure, "
        f"for {a_run - b_run:+.1f} s of scan time ({100 * (a_run - b_run) / b_run:+.0f} %)"
    )


if __name__ == "__main__":
    main()
