"""REST service under load: many clients poll a running scan; does the scan slow down, how fast are answers?

Usage: .venv/bin/python benchmarks/service.py [--frames 500] [--clients 50] [--detector 768]
       [--poll-interval-s 0.1] [--streams 5] [--time-scale 1.0] [--repeats 2] [--max-s 600]
Starts ``orbitct serve --sim`` in its own process on loopback, runs the same scan alone and with
the clients polling ``GET /scans/{id}`` and following ``/scans/{id}/events`` (pairs interleaved), and
prints the frame rates, the drop, status latency percentiles and the emergency-stop latency
under load. Targets (issue 7): frame rate drop < 10 %, p99 status latency < 50 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import yaml
from machine_info import cpu_model as cpu_name  # noqa: E402

# this file is named like nothing it imports, but keep its folder off the import path anyway
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
ROOT = Path(__file__).resolve().parents[1]
TOKEN = "oct_benchmark_dev_token_0123456789"
ORBIT = {"orbit": "sawtooth", "params": {"amplitude_deg": 6.0, "cycles": 2}, "errors": "none"}


def free_port() -> int:
    """An unused loopback port."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_service(folder: Path, detector: int, time_scale: float) -> tuple[subprocess.Popen[bytes], str]:
    """``orbitct serve --sim`` in a subprocess; returns it and its base URL once the bench is connected."""
    cfg = yaml.safe_load((ROOT / "config" / "bench.yaml").read_text())
    cfg["geometry"]["detector"] = {"rows": detector, "cols": detector}
    cfg["sim"]["time_scale"] = time_scale
    (folder / "bench.yaml").write_text(yaml.safe_dump(cfg))
    port = free_port()
    env = {**os.environ, "ORBITCT_DEV_TOKEN": TOKEN, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "orbitct_app.cli.main", "serve", "--config", str(folder / "bench.yaml"), "--sim",
         "--port", str(port), "--data-dir", str(folder / "data"), "--log-level", "warning"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
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


async def run_scan(client: httpx.AsyncClient, frames: int, max_s: float) -> tuple[str, dict[str, Any]]:
    """Start a scan and wait for its end; returns its id and final record."""
    r = await client.post("/scans", json={**ORBIT, "frames": frames})
    if r.status_code != 202:
        raise SystemExit(f"scan refused: {r.status_code} {r.text}")
    scan_id = r.json()["id"]
    t0 = time.monotonic()
    while time.monotonic() - t0 < max_s:
        body = (await client.get(f"/scans/{scan_id}")).json()
        if body["state"] not in ("queued", "running", "paused"):
            return scan_id, body
        await asyncio.sleep(0.25)
    await client.post(f"/scans/{scan_id}/abort")
    raise SystemExit(f"scan did not end within {max_s} s")


def frame_rate(scan: dict[str, Any]) -> float:
    """Frames per second of the scan body (all frames over the engine's run time)."""
    summary = scan["summary"]
    return summary["n_frames"] / summary["timing"]["run_s"]


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
        length = next(int(v) for k, _, v in (line.partition(":") for line in lines[1:]) if k.lower() == "content-length")
        return status, await self.reader.readexactly(length)

    async def close(self) -> None:
        """Close the connection."""
        if self.writer is not None:
            self.writer.close()
            await self.writer.wait_closed()


async def poller(base: str, scan_id: str, stop: asyncio.Event, interval_s: float,
                 latencies: list[float], errors: list[int]) -> None:
    """Poll the scan's status until ``stop``; latency of every answer."""
    client = KeepAliveClient(base)
    try:
        while not stop.is_set():
            t = time.perf_counter()
            status, _ = await client.get(f"/scans/{scan_id}")
            latencies.append(time.perf_counter() - t)
            if status != 200:
                errors.append(status)
            await asyncio.sleep(interval_s)
    finally:
        await client.close()


async def follower(client: httpx.AsyncClient, scan_id: str, seen: list[int]) -> None:
    """Follow the scan's event stream to its end, checking that ids arrive in order."""
    last = 0
    async with client.stream("GET", f"/scans/{scan_id}/events", timeout=None) as r:
        async for line in r.aiter_lines():
            if line.startswith("id:"):
                n = int(line[3:])
                if n != last + 1:
                    raise AssertionError(f"event {n} after {last}")
                last = n
    seen.append(last)


async def loaded_scan(base: str, args: argparse.Namespace) -> dict[str, Any]:
    """The scan with ``clients`` pollers and ``streams`` event followers; then an emergency stop under load."""
    headers = {"Authorization": f"Bearer {TOKEN}"}
    limits = httpx.Limits(max_connections=args.streams + 4)
    async with httpx.AsyncClient(base_url=base, headers=headers, limits=limits, timeout=30) as client:
        r = await client.post("/scans", json={**ORBIT, "frames": args.frames})
        if r.status_code != 202:
            raise SystemExit(f"scan refused: {r.status_code} {r.text}")
        scan_id = r.json()["id"]
        stop = asyncio.Event()
        latencies: list[float] = []
        errors: list[int] = []
        seen: list[int] = []
        tasks = [asyncio.create_task(poller(base, scan_id, stop, args.poll_interval_s, latencies, errors))
                 for _ in range(args.clients)]
        streams = [asyncio.create_task(follower(client, scan_id, seen)) for _ in range(args.streams)]
        t0 = time.monotonic()
        while time.monotonic() - t0 < args.max_s:
            body = (await client.get(f"/scans/{scan_id}")).json()
            if body["state"] not in ("queued", "running", "paused"):
                break
            await asyncio.sleep(0.25)
        stop.set()
        await asyncio.gather(*tasks)
        await asyncio.wait_for(asyncio.gather(*streams), 30)

        # emergency stop while the pollers hammer a second scan
        r = await client.post("/scans", json={**ORBIT, "frames": args.frames})
        second = r.json()["id"]
        while (await client.get(f"/scans/{second}")).json()["progress"].get("done", 0) < 10:
            await asyncio.sleep(0.05)
        stop2 = asyncio.Event()
        load = [asyncio.create_task(poller(base, second, stop2, args.poll_interval_s, [], []))
                for _ in range(args.clients)]
        await asyncio.sleep(1.0)
        t = time.perf_counter()
        r = await client.post("/stop")
        stop_s = time.perf_counter() - t
        stop2.set()
        await asyncio.gather(*load)
        halted = r.json().get("halted")
        final = (await client.get(f"/scans/{scan_id}")).json()
        return {"scan": final, "latencies": np.asarray(latencies), "errors": errors, "streams": seen,
                "stop_s": stop_s, "halted": halted, "requests": len(latencies), "poll_s": time.monotonic() - t0}


async def baseline(base: str, args: argparse.Namespace) -> dict[str, Any]:
    """The same scan with nobody polling (one status request every 0.25 s)."""
    async with httpx.AsyncClient(base_url=base, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30) as client:
        await run_scan(client, 10, args.max_s)  # warm-up: numba caches, twin start
        _, body = await run_scan(client, args.frames, args.max_s)
        return body


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=500, help="projections per scan (default 500)")
    ap.add_argument("--clients", type=int, default=50, help="concurrent status pollers (default 50)")
    ap.add_argument("--streams", type=int, default=5, help="clients following the event stream (default 5)")
    ap.add_argument("--detector", type=int, default=768, help="simulated panel rows = cols (default 768)")
    ap.add_argument("--poll-interval-s", type=float, default=0.1, help="pause between one client's polls (default 0.1)")
    ap.add_argument("--time-scale", type=float, default=1.0, help="twin speed-up (default 1 = real time)")
    ap.add_argument("--repeats", type=int, default=2, help="alone/loaded scan pairs, interleaved (default 2)")
    ap.add_argument("--max-s", type=float, default=600.0, help="give up a scan after this long (default 600)")
    args = ap.parse_args()
    if not (1 <= args.clients <= 500 and 2 <= args.frames <= 5000 and 0 <= args.streams <= 50 and 1 <= args.repeats <= 10):
        raise SystemExit("bounds: 1..500 clients, 2..5000 frames, 0..50 streams, 1..10 repeats")

    print(f"machine: {cpu_name()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(f"scan: sawtooth, {args.frames} projections, {args.detector}^2 px, twins x{args.time_scale:g}; "
          f"{args.clients} pollers every {args.poll_interval_s:g} s + {args.streams} event streams")
    with tempfile.TemporaryDirectory(prefix="orbitct-bench-") as tmp:
        proc, base = start_service(Path(tmp), args.detector, args.time_scale)
        try:
            alone, loaded = [], []
            for _ in range(args.repeats):  # interleaved, so that drifts of the machine's load hit both alike
                alone.append(asyncio.run(baseline(base, args)))
                loaded.append(asyncio.run(loaded_scan(base, args)))
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
    fps0_runs = [frame_rate(a) for a in alone]
    fps1_runs = [frame_rate(r["scan"]) for r in loaded]
    fps0, fps1 = float(np.mean(fps0_runs)), float(np.mean(fps1_runs))
    drop = 100.0 * (fps0 - fps1) / fps0
    lat = np.concatenate([r["latencies"] for r in loaded]) * 1000.0
    p50, p95, p99, pmax = (float(np.percentile(lat, q)) for q in (50, 95, 99, 100))
    requests = sum(r["requests"] for r in loaded)
    rate = requests / sum(r["poll_s"] for r in loaded)
    errors = sum(len(r["errors"]) for r in loaded)
    streams = sum(len(r["streams"]) for r in loaded)
    stops = [r["stop_s"] * 1000 for r in loaded]
    runs = lambda v: " / ".join(f"{x:.2f}" for x in v)  # noqa: E731
    rows = [
        ("frame rate alone (fps)", f"{fps0:.2f} (runs {runs(fps0_runs)})", ""),
        ("frame rate under load (fps)", f"{fps1:.2f} (runs {runs(fps1_runs)})", ""),
        ("frame rate drop", f"{drop:.1f} %", "< 10 %"),
        ("status requests answered", f"{requests} ({rate:.0f}/s), errors {errors}", ""),
        ("status latency p50 / p95", f"{p50:.1f} / {p95:.1f} ms", ""),
        ("status latency p99", f"{p99:.1f} ms", "< 50 ms"),
        ("status latency max", f"{pmax:.1f} ms", ""),
        ("event streams in order, complete", f"{streams}/{args.streams * args.repeats}", ""),
        ("emergency stop under load", f"{max(stops):.0f} ms (worst), halted={all(r['halted'] for r in loaded)}", ""),
    ]
    width = max(len(r[0]) for r in rows)
    print(f"\n{'measure':<{width}}  {'value':<40} target")
    for name, value, target in rows:
        print(f"{name:<{width}}  {value:<40} {target}")
    ok = drop < 10.0 and p99 < 50.0
    print(f"\ntargets {'met' if ok else 'NOT met'}")


if __name__ == "__main__":
    main()
