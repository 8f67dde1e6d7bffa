"""Benchmark: the first calibration and reconstruction after installing orbitct against the same run warm.

The first use after installation compiles the numerical kernels (numba), which are then cached on disk. This script
runs each command twice as a user would, `orbitct calibrate` on experiment A (200 views of 384 x 384), then FDK and
4 PWLS iterations on its calibrated geometry, and prints the wall time of each run, the compile time the command
itself reports, and cold over warm (target of issue 48: within 2x).

    python benchmarks/cold_start.py           # this environment with an empty kernel cache (NUMBA_CACHE_DIR)
    python benchmarks/cold_start.py --pip     # a fresh virtual environment: the wheel of this checkout, pip install

With ``--pip`` the wheel is built from a copy of this checkout's last commit, installed with its dependencies from the package index into a
new virtual environment in a temporary folder, and that environment's ``orbitct`` runs the commands (its kernels
never compiled before). Without it, only the kernel cache is fresh: the same compile work, without the install.
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

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

from machine_info import describe_machine

COMPILED = re.compile(r"first use after installation: ([0-9.]+) s compiling")
COMMANDS = (
    ("calibrate", ["calibrate", "{scan}", "--accept-poor"]),
    ("reconstruct FDK", ["reconstruct", "{scan}", "--algorithm", "fdk", "--shape", "64,64,64", "--yes"]),
    (
        "reconstruct PWLS (4 iterations)",
        ["reconstruct", "{scan}", "--algorithm", "pwls", "--iterations", "4", "--shape", "64,64,64", "--yes"],
    ),
)


def _run(orbitct: list[str], args: list[str], env: dict[str, str]) -> tuple[float, float]:
    """Wall seconds of one command and the compile seconds it reported (0 when it said none)."""
    t = time.perf_counter()
    done = subprocess.run([*orbitct, *args], env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t
    if done.returncode not in (0, 3):  # 3: a calibration whose check failed (its geometry is still written)
        raise SystemExit(f"orbitct {' '.join(args)} failed ({done.returncode}):\n{done.stdout}{done.stderr}")
    found = COMPILED.search(done.stdout + done.stderr)
    return wall, float(found.group(1)) if found else 0.0


def _fresh_environment(work: Path) -> list[str]:
    """A new virtual environment holding the wheel of this checkout's last commit (built from a copy of it, so
    the checkout gains no build folder); its ``orbitct`` command."""
    source = work / "source"
    source.mkdir()
    archive = subprocess.run(["git", "-C", str(_HERE.parent), "archive", "HEAD"], check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(source)], input=archive.stdout, check=True)
    subprocess.run(
        [sys.executable, "-m", "build", "--wheel", "--outdir", str(work / "dist"), str(source)],
        check=True,
        capture_output=True,
    )
    wheel = next((work / "dist").glob("orbitct-*.whl"))
    venv = work / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(venv / "bin" / "pip"), "install", "--quiet", str(wheel)], check=True)
    return [str(venv / "bin" / "orbitct")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pip", action="store_true", help="install the wheel into a fresh virtual environment first")
    args = ap.parse_args()
    print(describe_machine())
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
        if args.pip:
            t = time.perf_counter()
            orbitct = _fresh_environment(work)
            print(
                f"wheel built and installed with its dependencies into a fresh environment in {time.perf_counter() - t:.0f} s"
            )
            where = "a fresh virtual environment (pip install of this checkout's wheel)"
        else:
            orbitct = [str(Path(sys.executable).parent / "orbitct")]
            env["NUMBA_CACHE_DIR"] = str(work / "numba-cache")
            where = "this environment with an empty kernel cache"
        scan = work / "A.h5"
        subprocess.run(
            [*orbitct, "simulate", "-e", "A", "--frames", "200", "--detector-size", "384", "--out", str(scan)],
            env={**env, "NUMBA_CACHE_DIR": str(work / "simulator-cache")},  # the simulator's kernels stay apart
            check=True,
            capture_output=True,
        )
        rows = []
        for name, template in COMMANDS:
            timings = []
            for run in ("cold", "warm"):
                copy = work / f"{run}.h5"
                copy.write_bytes(scan.read_bytes())
                if name != "calibrate":  # reconstructions start from a calibrated scan, calibrated warm beforehand
                    _run(orbitct, ["calibrate", str(copy), "--accept-poor"], env)
                timings.append(_run(orbitct, [a.format(scan=copy) for a in template], env))
            (cold, compiled), (warm, _) = timings
            rows.append((name, cold, compiled, warm, cold / warm))
    print(
        f"\nfirst run after installation ({where}) against the second run, experiment A, 200 views of 384 x 384; "
        "the rows in the order a first session runs them (each first run compiles what the rows above did not)"
    )
    print("| command | first run s | of which compiling s | second run s | first / second |")
    print("| --- | --- | --- | --- | --- |")
    for name, cold, compiled, warm, ratio in rows:
        print(f"| {name} | {cold:.1f} | {compiled:.1f} | {warm:.1f} | {ratio:.1f} |")
    print("\ntarget (issue 48): the first run within 2x of the second")
    print(f"1-min load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
