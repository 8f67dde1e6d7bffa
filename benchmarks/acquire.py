"""Acquisition benchmark: a sawtooth scan on the in-process twins, timed per part.

Reports the whole scan time and, per frame, the time spent in detector acquisition
(X-ray exposure, rendering on the twin, frame transfer), in commanded motion and
settling (twin mechanics, scaled by --time-scale), and the rest: what the executor
and the recorder add (read-backs, bookkeeping, HDF5 write and flush, progress).

    .venv/bin/python benchmarks/acquire.py                       # 500 frames at 768 x 768 (targets)
    .venv/bin/python benchmarks/acquire.py --frames 100 --size 256   # quicker
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acquire.config import BenchConfig, load_config  # noqa: E402
from acquire.errors import AcquireError  # noqa: E402
from acquire.runner import ScanRequest, run_scan  # noqa: E402
from orbitct.scanfile import ScanFile  # noqa: E402
from machine_info import describe_machine as machine  # noqa: E402

TARGET_OVERHEAD_MS = 10.0
TARGET_TOTAL_S = 60.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=500, help="projections (default 500)")
    ap.add_argument("--size", type=int, default=768, help="detector pixels, square (default 768)")
    ap.add_argument("--mode", choices=["step", "continuous"], default="step")
    ap.add_argument("--time-scale", type=float, default=50.0,
                    help="twins move this many times faster than a real bench (default 50: mechanics out of the way)")
    ap.add_argument("--tilt-deg", type=float, default=8.0, help="sawtooth tilt amplitude (the hexapod twin allows ~8 with errors)")
    ap.add_argument("--frame-rate", type=float, default=None, help="continuous mode: frames per second")
    ap.add_argument("--overlap-readout", action="store_true",
                    help="step mode: move to the next frame while the panel reads out (config motion.overlap_readout)")
    ap.add_argument("--out", type=Path, default=None, help="keep the scan file here (default: a temporary folder)")
    args = ap.parse_args()

    cfg = load_config(ROOT / "config" / "bench.yaml")
    assert isinstance(cfg, BenchConfig)
    cfg = cfg.with_detector_size(args.size)
    cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"time_scale": args.time_scale}),
                                 "motion": cfg.motion.model_copy(update={"overlap_readout": args.overlap_readout})})
    tmp = tempfile.TemporaryDirectory()
    out = args.out or Path(tmp.name) / "bench.h5"
    req = ScanRequest(config=cfg, out=out, orbit="sawtooth", frames=args.frames,
                      orbit_params={"amplitude_deg": args.tilt_deg}, errors="bench", seed=0, mode=args.mode,
                      sim=True, frame_rate_hz=args.frame_rate, overwrite=True)
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
        ("mode / twin time scale", f"{args.mode}{' + overlapped readout' if args.overlap_readout else ''} / "
                                   f"{args.time_scale:g}x", ""),
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


if __name__ == "__main__":
    main()
