"""Benchmark the GCS device layer on loopback: command round trips and moves per second.

Run: ``.venv/bin/python benchmarks/devices.py [--n 2000]``. Prints a table and the
machine it ran on. Target: median ``POS?`` round trip under 1 ms over loopback TCP.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

# this script is called devices.py: keep its folder off the path so `devices` is the package
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]

from machine_info import describe_machine as machine

from devices.hexapod import Hexapod
from devices.twins.gcs import start_twin


async def _timed(n: int, fn: Callable[[], Awaitable[Any]]) -> list[float]:
    for _ in range(min(50, n)):
        await fn()
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        await fn()
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def _row(name: str, ms: list[float], note: str = "") -> str:
    ms_sorted = sorted(ms)
    p95 = ms_sorted[int(0.95 * (len(ms) - 1))]
    return f"| {name:<38} | {len(ms):>6} | {statistics.median(ms):>8.3f} | {p95:>8.3f} | {1e3 / statistics.mean(ms):>9.0f} | {note}"


async def run(n: int, moves: int) -> list[str]:
    rows = []
    server = start_twin("hexapod", world=None, time_scale=1e6)
    try:
        dev = Hexapod("hexapod", server.uri, poll_s=0.0)
        await dev.connect()
        await dev.reference()
        await dev.set_velocity(20.0)
        rows.append(_row("POS? (6 axes) over TCP", await _timed(n, dev.position), "target < 1 ms median"))
        rows.append(_row("#5 motion status (single char) TCP", await _timed(n, dev.moving)))
        rows.append(
            _row(
                "set command + ERR? (VLS) TCP", await _timed(n // 2, lambda: dev.set_velocity(20.0)), "two round trips"
            )
        )
        step = {"i": 0}

        async def raw_mov() -> None:
            step["i"] += 1
            await dev.client.command(f"MOV X {0.001 * (step['i'] % 100):.6f}")

        rows.append(_row("MOV + ERR? issued (no wait) TCP", await _timed(n // 2, raw_mov), "issue rate of moves"))

        async def full_move() -> None:
            step["i"] += 1
            await dev.move({"X": 0.001 * (step["i"] % 100), "U": 0.001 * (step["i"] % 7)})

        rows.append(
            _row("move(): limits+VMO?+MOV+wait on target", await _timed(moves, full_move), "complete moves, travel ~0")
        )
        path = server.run_sync(server.twin.open_serial)
        sdev = Hexapod("hexapod", f"serial://{path}?baud=115200")
        await sdev.connect()
        rows.append(
            _row("POS? (6 axes) over pty serial", await _timed(n // 2, sdev.position), "pseudo-terminal, no baud delay")
        )
        await sdev.close()
        await dev.close()
        rows.append(_pipython_row(server, n // 2))
    finally:
        server.stop()
    return rows


def _pipython_row(server: Any, n: int) -> str:
    try:
        from pipython import GCSDevice
        from pipython.pidevice.interfaces.pisocket import PISocket
    except ImportError:
        return "| PIPython qPOS (not installed)"

    class Gateway(PISocket):  # PIPython closes its gateway again on delete; make that harmless
        def close(self) -> None:
            if self.connected:
                super().close()

    gateway = Gateway(autoconnect=False)
    gateway.ConnectTCPIP(server.host, server.port)
    with GCSDevice(gateway=gateway) as pidev:
        pidev.axes  # noqa: B018 - caches SAI?
        ms = []
        for _ in range(n):
            t0 = time.perf_counter()
            pidev.qPOS()
            ms.append((time.perf_counter() - t0) * 1e3)
    return _row("PIPython qPOS() (incl. its ERR?)", ms, "PI's library, for comparison")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=2000, help="round trips per query row")
    parser.add_argument("--moves", type=int, default=300, help="complete moves in the move() row")
    args = parser.parse_args()
    rows = asyncio.run(run(args.n, args.moves))
    print(f"machine: {machine()}")
    print("| operation                              |      n | median ms |   p95 ms |  per second | note")
    print("|----------------------------------------|--------|-----------|----------|-------------|-----")
    for r in rows:
        print(r)


if __name__ == "__main__":
    main()
