"""Benchmark: is the test suite a reliable signal? The same suite under other thread counts, CPU kernels and load.

Runs pytest (as ``make test`` does) once per condition and reports, per condition, what passed and failed, and, for
every bound the tests record through ``tests/helpers/measured.py`` (calibration errors, how far a continuous sweep
ran past its angles), the value in each condition, the spread between them and the margin of the bound over the
worst value. A bound whose margin is small next to the spread is the next flaky test.

Conditions: ``threads2`` (numba and OpenBLAS on 2 threads, as CI), ``threads1`` (1 thread: other reduction orders),
``hog`` (2 threads with twice as many busy processes as cores beside the suite), and OpenBLAS kernels of other CPU
families (``haswell``, ``zen``, ``sandybridge``: other floating-point paths in the linear algebra, as on another
machine).

    python benchmarks/suite_stability.py                          # whole suite: threads2, threads1, hog (~45 min)
    python benchmarks/suite_stability.py --conditions threads2,zen,hog -- -m "realtime or slow" tests/calib
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

from machine_info import cores_available, describe_machine

ROOT = _HERE.parent
MEASURES_ENV = "ORBITCT_TEST_MEASURES"  # tests/helpers/measured.py (benchmarks do not import the tests)

CONDITIONS: dict[str, dict[str, str]] = {
    "threads2": {"NUMBA_NUM_THREADS": "2", "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2"},
    "threads1": {"NUMBA_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"},
    "hog": {"NUMBA_NUM_THREADS": "2", "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2"},
    "haswell": {"OPENBLAS_CORETYPE": "Haswell"},
    "zen": {"OPENBLAS_CORETYPE": "Zen"},
    "sandybridge": {"OPENBLAS_CORETYPE": "SandyBridge"},
}


@dataclass
class Outcome:
    """One run of the suite: its counts, failures, time, load, and the bounds it measured."""

    condition: str
    passed: int = 0
    failed: list[str] = field(default_factory=list)
    skipped: int = 0
    seconds: float = 0.0
    load: tuple[float, float] = (0.0, 0.0)
    measures: list[dict] = field(default_factory=list)


def _hog(n: int) -> list[subprocess.Popen]:
    """``n`` processes that keep a core busy each, at normal priority (as a user's other work would)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _junit(path: Path) -> tuple[int, list[str], int]:
    if not path.exists():
        return 0, ["(pytest wrote no report)"], 0
    passed, failed, skipped = 0, [], 0
    for case in ET.parse(path).getroot().iter("testcase"):
        name = f"{case.get('classname', '')}::{case.get('name', '')}"
        if case.find("failure") is not None or case.find("error") is not None:
            failed.append(name)
        elif case.find("skipped") is not None:
            skipped += 1
        else:
            passed += 1
    return passed, failed, skipped


def run(condition: str, pytest_args: list[str], workers: int, hog: int) -> Outcome:
    """Run the suite once under ``condition``."""
    with tempfile.TemporaryDirectory(prefix="orbitct-stability-") as tmp:
        measures, report = Path(tmp) / "measures.jsonl", Path(tmp) / "junit.xml"
        env = {**os.environ, **CONDITIONS[condition], MEASURES_ENV: str(measures)}
        cmd = [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            f"--junitxml={report}",
            *(["-n", str(workers), "--dist", "loadfile"] if workers > 1 else []),
            *pytest_args,
        ]
        hogs = _hog(hog) if condition == "hog" else []
        load0, t0 = os.getloadavg()[0], time.perf_counter()
        try:
            subprocess.run(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
        finally:
            load1 = os.getloadavg()[0]
            for p in hogs:
                p.kill()
                p.wait()
        out = Outcome(condition, seconds=time.perf_counter() - t0, load=(load0, load1))
        out.passed, out.failed, out.skipped = _junit(report)
        if measures.exists():
            out.measures = [json.loads(line) for line in measures.read_text().splitlines() if line.strip()]
    return out


def report(outcomes: list[Outcome], top: int) -> None:
    """Print the conditions, the failures, and each measured bound's spread and margin."""
    print(f"\n{'condition':<12} {'passed':>7} {'failed':>7} {'skipped':>8} {'time_s':>8}  load start -> end  env")
    for o in outcomes:
        env = " ".join(f"{k}={v}" for k, v in CONDITIONS[o.condition].items())
        print(
            f"{o.condition:<12} {o.passed:>7} {len(o.failed):>7} {o.skipped:>8} {o.seconds:>8.0f}  "
            f"{o.load[0]:>5.2f} -> {o.load[1]:<5.2f}   {env}"
        )
    for o in outcomes:
        for name in o.failed:
            print(f"  FAILED under {o.condition}: {name}")
    values: dict[tuple[str, str], dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    bounds: dict[tuple[str, str], float] = {}
    for o in outcomes:
        for m in o.measures:
            key = (m["test"], m["name"])
            values[key][o.condition].append(m["value"])
            bounds[key] = m["bound"]
    if not values:
        print("\nno bounds were measured (the selected tests record none)")
        return
    rows = []
    for key, per in values.items():
        worst = {c: max(v) for c, v in per.items()}
        hi, lo = max(worst.values()), min(worst.values())
        rows.append((bounds[key] / hi if hi > 0 else float("inf"), key, lo, hi, worst))
    rows.sort(key=lambda r: r[0])
    conds = [o.condition for o in outcomes]
    print(
        f"\nbounds, tightest first ({min(top, len(rows))} of {len(rows)}): the worst value per condition; "
        "spread = max - min over conditions; margin = bound / max"
    )
    print(
        f"{'test':<70} {'measure':<22} {'bound':>8} "
        + " ".join(f"{c:>10}" for c in conds)
        + f" {'spread':>8} {'margin':>7}"
    )
    for margin, (test, name), lo, hi, worst in rows[:top]:
        short = test.split("::", 1)[-1][:70]
        print(
            f"{short:<70} {name:<22} {bounds[(test, name)]:>8.4g} "
            + " ".join(f"{worst[c]:>10.4g}" if c in worst else f"{'-':>10}" for c in conds)
            + f" {hi - lo:>8.3g} {margin:>6.2f}x"
        )


def main() -> None:
    """Parse the options, run every condition, print the tables."""
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], epilog="Arguments after -- go to pytest (default: the whole suite)."
    )
    ap.add_argument(
        "--conditions",
        default="threads2,threads1,hog",
        help=f"comma-separated, of {', '.join(CONDITIONS)} (default: %(default)s)",
    )
    ap.add_argument("--workers", type=int, default=2, help="pytest-xdist processes, as make test (default: 2)")
    ap.add_argument(
        "--hog",
        type=int,
        default=2 * cores_available(),
        help="busy processes beside the suite in the hog condition (default: twice the cores)",
    )
    ap.add_argument("--top", type=int, default=40, help="bounds to list (default: 40)")
    args, rest = ap.parse_known_args()
    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    unknown = [c for c in conditions if c not in CONDITIONS]
    if unknown:
        ap.error(f"unknown condition {', '.join(unknown)}; choose from {', '.join(CONDITIONS)}")
    pytest_args = [a for a in rest if a != "--"]
    print(f"suite stability: {describe_machine()}")
    print(f"pytest {' '.join(pytest_args) or '(whole suite)'}, {args.workers} workers, hog {args.hog} processes")
    outcomes = []
    for condition in conditions:
        outcomes.append(run(condition, pytest_args, args.workers, args.hog))
        o = outcomes[-1]
        print(f"  {condition}: {o.passed} passed, {len(o.failed)} failed in {o.seconds:.0f} s", flush=True)
    report(outcomes, args.top)
    sys.exit(1 if any(o.failed for o in outcomes) else 0)


if __name__ == "__main__":
    main()
