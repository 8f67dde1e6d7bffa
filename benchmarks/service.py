"""REST service under load: many clients poll a running scan; does the scan slow down, how fast are answers,
how fast is the emergency stop?

Usage: .venv/bin/python benchmarks/service.py [--frames 300] [--clients 50,100] [--detector 768]
       [--poll-interval-s 0.1] [--streams 10] [--stops 30] [--time-scale 1.0] [--max-s 600]
Starts ``orbitct serve --sim`` in its own process on loopback. For each number of pollers: the
same scan alone and with the pollers on ``GET /scans/{id}`` (plus event-stream followers), then,
with the pollers and followers still at it, a second scan stopped through the guard's own listener and
repeated stops through it and through ``POST /stop`` on the main port. The pollers run in a process
of their own and the stop client in this one, so neither waits on the other's event loop.
Prints frame rates, status latency percentiles and stop latency percentiles (each stop: halt
every device and read each back).
Targets: frame rate drop < 10 %, p99 status latency < 50 ms, p99 stop latency through the guard < 100 ms
with 100 pollers and 10 event streams.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import h5py
import httpx
import numpy as np
import yaml

# this folder last on the import path (its scripts are named like modules of the project), the project first
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE.parent), str(_HERE)]
from machine_info import describe_machine

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "oct_benchmark_dev_token_0123456789"
ORBIT = {"orbit": "sawtooth", "params": {"amplitude_deg": 6.0, "cycles": 2}, "errors": "none"}


def free_port() -> int:
    """An unused loopback port."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_service(
    folder: Path, detector: int, time_scale: float, prep_ms: float | None = None
) -> tuple[subprocess.Popen[bytes], str]:
    """``orbitct serve --sim`` in a subprocess; returns it and its base URL once the bench is connected.

    ``prep_ms`` replaces the generator's preparation time of ``config/bench.yaml`` (None: keep it)."""
    cfg = yaml.safe_load((ROOT / "config" / "bench.yaml").read_text())
    cfg["geometry"]["detector"] = {"rows": detector, "cols": detector}
    cfg["sim"]["time_scale"] = time_scale
    if prep_ms is not None:
        cfg["exposure"]["prep_ms"] = prep_ms
    (folder / "bench.yaml").write_text(yaml.safe_dump(cfg))
    port = free_port()
    env = {**os.environ, "ORBITCT_DEV_TOKEN": TOKEN, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "orbitct_app.cli.main",
            "serve",
            "--config",
            str(folder / "bench.yaml"),
            "--sim",
            "--port",
            str(port),
            "--stop-port",
            "0",
            "--data-dir",
            str(folder / "data"),
            "--log-level",
            "warning",
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}"
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120:
        if proc.poll() is not None:
            raise SystemExit("the service exited during start-up")
        try:
            if httpx.get(f"{base}/health", timeout=1).json().get("bench") == "connected":
                return proc, base
        except (httpx.HTTPError, ValueError):
            pass
        time.sleep(0.2)
    proc.kill()
    raise SystemExit("the service did not start within 120 s")


def frame_rate(scan: dict[str, Any], data_dir: Path, skip: int = 20) -> float:
    """Steady frames per second of a scan's projections, from the frame times in its file, after the first ``skip``.

    Not the engine's run time: that includes the move to the first frame, which is longer for a scan that starts
    where another ended than for the first scan after referencing, and would bias a comparison of two scans."""
    with h5py.File(data_dir / "scans" / f"{scan['id']}.h5", "r") as f:
        keys = f["frames/image_key"][()]
        times = f["frames/time_s"][()][keys == 0][skip:]
    return (len(times) - 1) / float(times[-1] - times[0])


class KeepAliveClient:
    """A minimal HTTP/1.1 keep-alive GET client (so that the load generator itself stays cheap)."""

    def __init__(self, base: str) -> None:
        host, port = base.removeprefix("http://").split(":")
        self.host, self.port = host, int(port)
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def get(self, path: str) -> tuple[int, bytes]:
        """Status and body of ``GET path``."""
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        assert self.reader is not None
        self.writer.write(f"GET {path} HTTP/1.1\r\nHost: {self.host}\r\nAuthorization: Bearer {TOKEN}\r\n\r\n".encode())
        head = await self.reader.readuntil(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        length = next(
            int(v) for k, _, v in (line.partition(":") for line in lines[1:]) if k.lower() == "content-length"
        )
        return status, await self.reader.readexactly(length)

    async def close(self) -> None:
        """Close the connection."""
        if self.writer is not None:
            self.writer.close()
            await self.writer.wait_closed()


async def poller(
    base: str, path: str, stop: asyncio.Event, interval_s: float, latencies: list[float], errors: list[int]
) -> None:
    """GET ``path`` until ``stop``; latency of every answer."""
    client = KeepAliveClient(base)
    try:
        while not stop.is_set():
            t = time.perf_counter()
            status, _ = await client.get(path)
            latencies.append(time.perf_counter() - t)
            if status != 200:
                errors.append(status)
            await asyncio.sleep(interval_s)
    finally:
        await client.close()


async def follower(base: str, scan_id: str, seen: list[int]) -> None:
    """Follow the scan's event stream to its end, checking that ids arrive in order."""
    last = 0
    headers = {"Authorization": f"Bearer {TOKEN}"}
    async with (
        httpx.AsyncClient(base_url=base, headers=headers, timeout=None) as client,
        client.stream("GET", f"/scans/{scan_id}/events") as r,
    ):
        async for line in r.aiter_lines():
            if line.startswith("id:"):
                n = int(line[3:])
                if n != last + 1:
                    raise AssertionError(f"event {n} after {last}")
                last = n
    seen.append(last)


async def follower_of_running(base: str, stop: asyncio.Event, seen: list[int]) -> None:
    """Follow the event stream of whichever scan is running, one after the other, until ``stop``."""
    async with httpx.AsyncClient(base_url=base, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30) as client:
        followed: set[str] = set()
        while not stop.is_set():
            running = (await client.get("/scans", params={"state": "running", "limit": 1})).json()
            items = running.get("items", running) if isinstance(running, dict) else running
            new = [row["id"] for row in items if row["id"] not in followed]
            if not new:
                await asyncio.sleep(0.05)
                continue
            followed.add(new[0])
            await follower(base, new[0], seen)


def load_process(base: str, scan_id: str, clients: int, streams: int, interval_s: float, conn: Connection) -> None:
    """The pollers and followers, in a process of their own, until ``"stop"`` arrives; sends back what they saw.
    ``scan_id`` empty: the followers follow each running scan in turn."""

    async def run() -> dict[str, Any]:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        threading.Thread(target=lambda: (conn.recv(), loop.call_soon_threadsafe(stop.set)), daemon=True).start()
        latencies: list[float] = []
        errors: list[int] = []
        seen: list[int] = []
        t0 = time.monotonic()
        tasks = [
            asyncio.create_task(
                poller(base, f"/scans/{scan_id}" if scan_id else "/scans?limit=5", stop, interval_s, latencies, errors)
            )
            for _ in range(clients)
        ]
        followers = [
            asyncio.create_task(follower(base, scan_id, seen) if scan_id else follower_of_running(base, stop, seen))
            for _ in range(streams)
        ]
        conn.send("started")
        await stop.wait()
        await asyncio.gather(*tasks)
        for f in followers:
            f.cancel()
        await asyncio.gather(*followers, return_exceptions=True)
        return {"latencies": latencies, "errors": errors, "streams": len(seen), "poll_s": time.monotonic() - t0}

    conn.send(asyncio.run(run()))


class Load:
    """Pollers (and event followers) on a scan from another process, as a context manager."""

    def __init__(self, base: str, scan_id: str, clients: int, streams: int, interval_s: float) -> None:
        self._conn, child = mp.get_context("spawn").Pipe()
        self._proc = mp.get_context("spawn").Process(
            target=load_process, daemon=True, args=(base, scan_id, clients, streams, interval_s, child)
        )
        self.result: dict[str, Any] = {}

    def __enter__(self) -> Load:
        self._proc.start()
        if self._conn.recv() != "started":
            raise SystemExit("the load process did not start")
        return self

    def __exit__(self, *exc: object) -> None:
        self._conn.send("stop")
        self.result = self._conn.recv()
        self._proc.join(30)


def scan_started(client: httpx.Client, frames: int, taken: int = 10) -> str:
    """Start a scan and return once it has taken ``taken`` frames."""
    r = client.post("/scans", json={**ORBIT, "frames": frames})
    if r.status_code != 202:
        raise SystemExit(f"scan refused: {r.status_code} {r.text}")
    scan_id = r.json()["id"]
    while client.get(f"/scans/{scan_id}").json()["progress"].get("done", 0) < taken:
        time.sleep(0.05)
    return str(scan_id)


def scan_ended(client: httpx.Client, scan_id: str, max_s: float) -> dict[str, Any]:
    """Wait for a scan's end; its record."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < max_s:
        body = client.get(f"/scans/{scan_id}").json()
        if body["state"] not in ("queued", "running", "paused"):
            return dict(body)
        time.sleep(0.25)
    client.post(f"/scans/{scan_id}/abort")
    raise SystemExit(f"scan did not end within {max_s} s")


def stops_mid_scan(
    client: httpx.Client, stopper: httpx.Client, url: str, n: int, frames: int, max_s: float
) -> tuple[list[float], bool]:
    """``n`` stops at ``url``, each one while a scan runs (started, stopped, ended, reset): their latencies (s) and
    whether every one proved halted. ``stopper`` keeps one keep-alive connection, as `orbitct stop` would."""
    times, halted = [], True
    for _ in range(n):
        scan_id = scan_started(client, frames, taken=3)
        t = time.perf_counter()
        r = stopper.post(url, json={"reason": "benchmark"})
        times.append(time.perf_counter() - t)
        halted = halted and r.status_code == 202 and bool(r.json().get("halted"))
        if scan_ended(client, scan_id, max_s)["state"] != "aborted":
            halted = False
        client.post("/stop/reset", json={"note": "benchmark"})
    return times, halted


def under_load(base: str, clients: int, args: argparse.Namespace) -> dict[str, Any]:
    """One number of pollers: a scan alone, the same scan loaded, then stops under the same load."""
    headers = {"Authorization": f"Bearer {TOKEN}"}
    with httpx.Client(base_url=base, headers=headers, timeout=60) as client:
        alone = scan_ended(client, scan_started(client, args.frames), args.max_s)
        scan_id = scan_started(client, args.frames)
        with Load(base, scan_id, clients, args.streams, args.poll_interval_s) as load:
            loaded = scan_ended(client, scan_id, args.max_s)
        stop_url = client.get("/stop").json()["stop_url"]
        with Load(base, "", clients, args.streams, args.poll_interval_s) as stop_load:
            time.sleep(1.0)
            with (
                httpx.Client(headers=headers, timeout=30) as guard,
                httpx.Client(base_url=base, headers=headers, timeout=30) as rest,
            ):
                guard_s, guard_halted = stops_mid_scan(client, guard, stop_url, args.stops, args.frames, args.max_s)
                rest_s, rest_halted = stops_mid_scan(client, rest, "/stop", args.stops, args.frames, args.max_s)
    return {
        "alone": alone,
        "loaded": loaded,
        "load": load.result,
        "stop_load": stop_load.result,
        "guard_s": guard_s,
        "rest_s": rest_s,
        "halted": guard_halted and rest_halted,
    }


def pct(values: Any, q: float) -> float:
    """Percentile ``q`` of ``values`` in milliseconds."""
    return float(np.percentile(np.asarray(values) * 1000.0, q))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300, help="projections per scan (default 300)")
    ap.add_argument("--clients", default="50,100", help="numbers of concurrent status pollers (default 50,100)")
    ap.add_argument("--streams", type=int, default=10, help="clients following the event stream (default 10)")
    ap.add_argument("--stops", type=int, default=30, help="stops timed per path and load (default 30)")
    ap.add_argument("--detector", type=int, default=768, help="simulated panel rows = cols (default 768)")
    ap.add_argument("--poll-interval-s", type=float, default=0.1, help="pause between one client's polls (default 0.1)")
    ap.add_argument("--time-scale", type=float, default=1.0, help="twin speed-up (default 1 = real time)")
    ap.add_argument("--max-s", type=float, default=600.0, help="give up a scan after this long (default 600)")
    ap.add_argument(
        "--prep-ms",
        type=float,
        default=100.0,
        help="the generator's preparation time (default 100; "
        "config/bench.yaml's 200 puts this scan on the generator's hold threshold: see benchmarks/console.py)",
    )
    args = ap.parse_args()
    clients = [int(c) for c in args.clients.split(",")]
    if not (
        all(1 <= c <= 500 for c in clients)
        and 20 <= args.frames <= 5000
        and 0 <= args.streams <= 50
        and 2 <= args.stops <= 1000
    ):
        raise SystemExit("bounds: 1..500 clients, 20..5000 frames, 0..50 streams, 2..1000 stops")

    print(f"machine: {describe_machine()}")
    print(
        f"scan: sawtooth, {args.frames} projections, {args.detector}^2 px, twins x{args.time_scale:g}; "
        f"pollers every {args.poll_interval_s:g} s each + {args.streams} event streams; {args.stops} stops per path"
    )
    with tempfile.TemporaryDirectory(prefix="orbitct-bench-") as tmp:
        proc, base = start_service(Path(tmp), args.detector, args.time_scale, args.prep_ms)
        try:
            with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60) as client:
                scan_ended(client, scan_started(client, 20), args.max_s)  # warm-up: numba caches, twin start
            results = {n: under_load(base, n, args) for n in clients}
            rates = {
                n: (frame_rate(r["alone"], Path(tmp) / "data"), frame_rate(r["loaded"], Path(tmp) / "data"))
                for n, r in results.items()
            }
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
    rows = []
    ok = True
    for n, r in results.items():
        fps0, fps1 = rates[n]
        drop = 100.0 * (fps0 - fps1) / fps0
        lat = r["load"]["latencies"]
        status_p99 = pct(lat, 99)
        guard_p99 = pct(r["guard_s"], 99)
        rate = len(lat) / r["load"]["poll_s"]
        states = f"{r['alone']['state']} / {r['loaded']['state']}"
        rows += [
            (
                f"{n} pollers: scans alone / loaded",
                states + "".join(f" ({s['reason']})" for s in (r["alone"], r["loaded"]) if s["state"] != "complete"),
                "complete / complete",
            ),
            (
                f"{n} pollers: frame rate alone / loaded",
                f"{fps0:.2f} / {fps1:.2f} fps (drop {drop:.1f} %)",
                "drop < 10 %",
            ),
            (
                f"{n} pollers: status requests",
                f"{len(lat)} ({rate:.0f}/s), errors {len(r['load']['errors'])}, "
                f"streams {r['load']['streams']}/{args.streams}",
                "",
            ),
            (
                f"{n} pollers: status p50 / p95 / p99 / max",
                f"{pct(lat, 50):.1f} / {pct(lat, 95):.1f} / {status_p99:.1f} / {pct(lat, 100):.1f} ms",
                "p99 < 50 ms",
            ),
            (
                f"{n} pollers: stops mid-scan, load streams",
                f"{len(r['guard_s'])} + {len(r['rest_s'])}, {r['stop_load']['streams']} streams followed to their end",
                "",
            ),
            (
                f"{n} pollers: stop via guard p50 / p99 / max",
                f"{pct(r['guard_s'], 50):.1f} / {guard_p99:.1f} / {pct(r['guard_s'], 100):.1f} ms",
                "p99 < 100 ms",
            ),
            (
                f"{n} pollers: stop via POST /stop p50 / p99 / max",
                f"{pct(r['rest_s'], 50):.1f} / {pct(r['rest_s'], 99):.1f} / {pct(r['rest_s'], 100):.1f} ms",
                "",
            ),
            (f"{n} pollers: every stop proven halted, its scan aborted", f"{r['halted']}", "True"),
        ]
        ok = (
            ok
            and drop < 10.0
            and status_p99 < 50.0
            and guard_p99 < 100.0
            and r["halted"]
            and states == "complete / complete"
        )
    width = max(len(row[0]) for row in rows)
    print(f"\n{'measure':<{width}}  {'value':<58} target")
    for name, value, target in rows:
        print(f"{name:<{width}}  {value:<58} {target}")
    print(f"\ntargets {'met' if ok else 'NOT met'}; machine after the run: {describe_machine()}")


if __name__ == "__main__":
    main()
