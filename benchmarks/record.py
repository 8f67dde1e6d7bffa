"""Run benchmarks and keep what they printed: one JSON file per benchmark in ``benchmarks/results/``.

Each file holds the command, when it ran, how long it took, the machine and its load before and after, the exit
status and the benchmark's whole output (its table and the machine line it prints). The documentation's
performance page is made from these files when the site is built, so the figures there are the benchmarks' own,
never typed by hand. A benchmark that fails is recorded too, with its exit status.

    python benchmarks/record.py simulate devices                 # run these two, record each
    python benchmarks/record.py recon -- --threads 2             # arguments after -- go to the benchmark
    python benchmarks/record.py --quick                          # every benchmark that takes minutes, not hours
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

from machine_info import describe_machine

RESULTS = _HERE / "results"
#: the benchmarks that finish within minutes on 2 cores (the others take an hour or more, or need a cluster)
QUICK = (
    "simulate",
    "devices",
    "acquire",
    "calibrate",
    "live_calibration",
    "calibration_robustness",
    "pwls_acceleration",
    "recon",
    "estimates",
    "bb_planning",
    "service",
    "console",
    "cold_start",
)
#: scripts in benchmarks/ that are not benchmarks of orbitct itself
NOT_BENCHMARKS = {"record", "machine_info", "suite_stability"}


def benchmarks() -> list[str]:
    """Every benchmark script's name."""
    return sorted(p.stem for p in _HERE.glob("*.py") if p.stem not in NOT_BENCHMARKS)


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else []


def record(name: str, args: list[str], timeout_s: float) -> dict[str, object]:
    """Run one benchmark, write its result file, return what was written."""
    command = [sys.executable, str(_HERE / f"{name}.py"), *args]
    shown = " ".join(["python", f"benchmarks/{name}.py", *args])
    started = datetime.datetime.now(datetime.UTC)
    machine, load_before, t0 = describe_machine(), _load(), time.monotonic()
    print(f"== {shown}", flush=True)
    try:
        done = subprocess.run(command, cwd=_HERE.parent, capture_output=True, text=True, timeout=timeout_s, check=False)
        status, output = done.returncode, done.stdout + (f"\n{done.stderr}" if done.returncode else "")
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        status, output = -1, out + f"\n(stopped after {timeout_s:.0f} s)"
    result: dict[str, object] = {
        "benchmark": name,
        "command": shown,
        "started_utc": started.isoformat(timespec="seconds"),
        "seconds": round(time.monotonic() - t0, 1),
        "machine": machine,
        "load_before": load_before,
        "load_after": _load(),
        "exit_status": status,
        "output": output.rstrip(),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    print(output.rstrip(), flush=True)
    print(f"-- {name}: exit status {status} after {result['seconds']} s, recorded in benchmarks/results/{name}.json")
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help=f"benchmarks to run: {', '.join(benchmarks())}")
    parser.add_argument("--quick", action="store_true", help=f"run {', '.join(QUICK)}")
    parser.add_argument("--timeout-s", type=float, default=3 * 3600.0, help="stop a benchmark after this long")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    options, args = parser.parse_args(argv[:cut]), argv[cut + 1 :]  # after --: arguments for the benchmark(s)
    names = list(options.names) + (list(QUICK) if options.quick else [])
    unknown = sorted(set(names) - set(benchmarks()))
    if unknown or not names:
        parser.error(f"name benchmarks to run ({', '.join(benchmarks())}) or --quick; unknown: {unknown}")
    failed = [n for n in names if record(n, args, options.timeout_s)["exit_status"] != 0]
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
