"""The bench owned by the service: one thread with its own asyncio loop runs the devices and the scan.

Request handlers never do device I/O on the web server's loop: they submit coroutines to the
bench loop and read scan progress from an in-memory snapshot. The emergency stop takes no lock:
it asks the runner to abort and sends the halt to the bench loop at once.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from orbitct.progress import ProgressEvent
from orbitct.service.db import Store, utc_now
from orbitct.service.errors import Conflict, Unavailable
from orbitct.service.events import EventBus

log = logging.getLogger("orbitct.service.bench")
T = TypeVar("T")


@dataclass
class ActiveScan:
    """The scan on the bench now, with its latest progress (read without locks)."""

    scan_id: str
    path: Path
    runner: Any
    progress: dict[str, Any] = field(default_factory=dict)
    state: str = "queued"
    started: float = field(default_factory=time.monotonic)
    last_db: float = 0.0
    done: threading.Event = field(default_factory=threading.Event)


def scan_summary(path: Path) -> dict[str, Any]:
    """What a finished scan file holds: frames by kind, geometries, detector, orbit, status."""
    from orbitct.scanfile import ScanFile, ScanFileError

    try:
        with ScanFile(path) as sf:
            name, params = sf.orbit
            geometries = [g for g in ("nominal", "calibrated", "truth") if sf.has_geometry(g)]
            return {
                "status": sf.status, "status_reason": sf.status_reason, "n_frames": sf.n_frames,
                "frames_by_kind": sf.count_by_kind(), "detector": {"rows": sf.detector.rows, "cols": sf.detector.cols,
                                                                   "pitch_mm": list(sf.detector.pitch_mm)},
                "geometries": geometries, "orbit": {"name": name, "params": params},
                "recon": sf.recon_names(), "file_bytes": path.stat().st_size,
            }
    except (ScanFileError, OSError, KeyError, ValueError) as exc:
        return {"error": f"scan file unreadable: {exc}".replace(str(path), path.name)}


class BenchController:
    """Owns the bench connection and the one scan it may run at a time."""

    def __init__(self, config_path: Path, *, sim: bool, store: Store, bus: EventBus, data_dir: Path,
                 status_interval_s: float = 0.25) -> None:
        self.config_path = Path(config_path)
        self.sim = sim
        self._store, self._bus = store, bus
        self._data_dir = Path(data_dir)
        self._interval = status_interval_s
        self.config: Any = None
        self.bench: Any = None
        self.connection_state = "not started"
        self.current: ActiveScan | None = None
        self._start_lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stack: contextlib.AsyncExitStack | None = None
        self._db = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="orbitct-scan-db")

    # ------------------------------------------------------------ lifecycle
    def start(self, timeout_s: float = 60.0) -> None:
        """Load the configuration, start the bench thread and connect every device (twins with sim)."""
        ready = threading.Event()
        self._thread = threading.Thread(target=self._main, args=(ready,), name="orbitct-bench", daemon=True)
        self._thread.start()
        if not ready.wait(5.0):
            raise RuntimeError("bench thread did not start")
        try:
            from acquire.config import load_config

            self.config = load_config(self.config_path)
            self.call(self._connect(), timeout_s)
        except Exception as exc:  # noqa: BLE001 - the service still starts, degraded, and says why
            self.connection_state = f"failed: {exc}"
            log.error("bench connection failed: %s", exc)

    def _main(self, ready: threading.Event) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        loop.call_soon(ready.set)
        loop.run_forever()
        loop.run_until_complete(loop.shutdown_asyncgens())
        loop.close()

    async def _connect(self) -> None:
        from acquire.bench import open_bench
        from acquire.config import BenchConfig

        self.connection_state = "connecting"
        if not isinstance(self.config, BenchConfig):
            self.connection_state = "connected"  # C-arm scans connect per scan
            return
        self._stack = contextlib.AsyncExitStack()
        self.bench = await self._stack.enter_async_context(open_bench(self.config, sim=self.sim))
        self.connection_state = "connected"

    def close(self, reason: str = "service shutting down") -> None:
        """Abort a running scan, halt everything, disconnect and stop the bench thread."""
        active = self.current
        if active is not None:
            active.runner.abort(reason)
            active.done.wait(15.0)
        if self._loop is not None and self._loop.is_running():
            with contextlib.suppress(Exception):
                self.call(self._disconnect(), 15.0)
            self._loop.call_soon_threadsafe(self._loop.stop)
        if self._thread is not None:
            self._thread.join(10.0)
        self._db.shutdown(wait=True)
        self.connection_state = "closed"

    async def _disconnect(self) -> None:
        if self.bench is not None:
            with contextlib.suppress(Exception):
                await self.bench.stop_all()
        if self._stack is not None:
            await self._stack.aclose()
        self.bench = None

    def device_map(self) -> dict[str, Any]:
        """Connected devices by name (empty when not connected)."""
        bench = self.bench
        if bench is None:
            return {}
        return {d.name: d for d in bench.devices}

    # ------------------------------------------------------------ bench loop access
    def submit(self, coro: Awaitable[T]) -> concurrent.futures.Future[T]:
        """Run ``coro`` on the bench loop; returns a thread-safe future."""
        if self._loop is None or not self._loop.is_running():
            if asyncio.iscoroutine(coro):
                coro.close()
            raise Unavailable("the bench is not running")
        return asyncio.run_coroutine_threadsafe(coro, self._loop)  # type: ignore[arg-type]

    def call(self, coro: Awaitable[T], timeout_s: float = 30.0) -> T:
        """Run ``coro`` on the bench loop and wait for it (from a thread that is not the bench loop)."""
        return self.submit(coro).result(timeout_s)

    async def run(self, fn: Callable[[Any], Awaitable[T]], timeout_s: float = 30.0) -> T:
        """Await ``fn(bench)`` run on the bench loop, from the web server's loop."""
        if self.bench is None:
            raise Unavailable(f"the bench is not connected ({self.connection_state})")
        fut = self.submit(fn(self.bench))
        try:
            return await asyncio.wait_for(asyncio.wrap_future(fut), timeout_s)
        except asyncio.TimeoutError:
            fut.cancel()
            raise Unavailable(f"the bench did not answer within {timeout_s:g} s") from None

    # ------------------------------------------------------------ scans
    @property
    def busy(self) -> str | None:
        """Id of the scan on the bench, if any."""
        active = self.current
        return active.scan_id if active is not None else None

    def preflight(self, request: Any) -> None:
        """Plan and pre-flight ``request`` against every limit (raises PreflightError / AcquireError)."""
        from acquire.config import BenchConfig
        from acquire.preflight import preflight
        from acquire.runner import build_plan

        cfg = request.resolved_config()
        if not isinstance(cfg, BenchConfig) or self.bench is None:
            return
        plan = build_plan(request, cfg)
        bench = self.bench

        async def _check() -> None:
            await preflight(plan, cfg, device_limits=await bench.device_limits(),
                            workspace_check=bench.check_workspace, mode=request.mode,
                            frame_rate_hz=request.frame_rate_hz or cfg.exposure.frame_rate_hz)

        self.call(_check(), 60.0)

    def start_scan(self, scan_id: str, request: Any) -> ActiveScan:
        """Start ``request`` on the bench loop; 409 if a scan is already running."""
        from acquire.runner import ScanRunner

        if self.connection_state != "connected":
            raise Unavailable(f"the bench is not connected ({self.connection_state})")
        with self._start_lock:
            if self.current is not None:
                raise Conflict(f"the bench is busy with scan {self.current.scan_id}; one scan at a time")
            active = ActiveScan(scan_id, Path(request.out), None)
            active.runner = ScanRunner(request, progress=lambda ev: self._on_progress(active, ev), bench=self.bench)
            self.current = active
        try:
            self.submit(self._run_scan(active))
        except Exception:
            self.current = None
            raise
        return active

    async def _run_scan(self, active: ActiveScan) -> None:
        topic = f"scan:{active.scan_id}"
        self._set_state(active, "running", "")
        self._db.submit(self._store.update_scan, active.scan_id, state="running", started_utc=utc_now())
        state, reason = "failed", ""
        result: Any = None
        try:
            result = await active.runner.run()
            state, reason = result.status, result.reason
        except asyncio.CancelledError:
            state, reason = "aborted", "cancelled"
        except Exception as exc:  # noqa: BLE001 - pre-flight refusals, configuration and device errors
            state, reason = "failed", str(exc) or type(exc).__name__
        finally:
            loop = asyncio.get_running_loop()
            summary = await loop.run_in_executor(self._db, scan_summary, active.path) if active.path.exists() else {}
            if result is not None:
                summary["timing"] = {k: float(v) for k, v in dict(result.timing).items()}
                summary["elapsed_s"] = float(result.elapsed_s)
            fields = dict(state=state, reason=reason[:2000], finished_utc=utc_now(), summary=summary,
                          frames_done=int(summary.get("n_frames", active.progress.get("done", 0))), progress=active.progress)
            if active.progress.get("total"):
                fields["frames_total"] = int(active.progress["total"])
            await loop.run_in_executor(self._db, lambda: self._store.update_scan(active.scan_id, **fields))
            self._set_state(active, state, reason)
            self._bus.publish(topic, "end", {"state": state, "reason": reason})
            self.current = None
            active.done.set()

    def _set_state(self, active: ActiveScan, state: str, reason: str) -> None:
        active.state = state
        self._bus.publish(f"scan:{active.scan_id}", "state", {"state": state, "reason": reason})

    def _on_progress(self, active: ActiveScan, event: ProgressEvent) -> None:
        """Per-frame callback on the bench loop: snapshot, event, and a throttled DB write (off-thread)."""
        data = {"stage": event.stage, "done": int(event.done), "total": int(event.total), "message": event.message,
                "metrics": {k: float(v) for k, v in dict(event.metrics).items()}}
        active.progress = data
        if event.message == "paused" and active.state != "paused":
            self._set_state(active, "paused", "")
        elif active.state == "paused" and event.message != "paused" and event.stage == "scan" and event.done > 0:
            self._set_state(active, "running", "")
        self._bus.publish(f"scan:{active.scan_id}", "progress", data)
        now = time.monotonic()
        if now - active.last_db >= self._interval:
            active.last_db = now
            self._db.submit(self._store.update_scan, active.scan_id, frames_done=data["done"], frames_total=data["total"],
                            progress=data)

    def pause(self, scan_id: str) -> None:
        """Pause the running scan at the next frame boundary."""
        from acquire.errors import ScanStateError

        try:
            self._active(scan_id).runner.pause()
        except ScanStateError as exc:
            raise Conflict(str(exc)) from None

    def resume(self, scan_id: str) -> None:
        """Resume a paused scan."""
        from acquire.errors import ScanStateError

        active = self._active(scan_id)
        try:
            active.runner.resume()
        except ScanStateError as exc:
            raise Conflict(str(exc)) from None
        if active.state == "paused":
            self._set_state(active, "running", "")

    def abort(self, scan_id: str, reason: str) -> ActiveScan:
        """Abort the running scan (halt, X-rays off, file marked aborted)."""
        active = self._active(scan_id)
        active.runner.abort(reason)
        return active

    def _active(self, scan_id: str) -> ActiveScan:
        active = self.current
        if active is None or active.scan_id != scan_id:
            raise Conflict(f"scan {scan_id} is not running on the bench")
        return active

    # ------------------------------------------------------------ emergency stop
    def emergency_stop(self, reason: str) -> tuple[str | None, concurrent.futures.Future[None] | None]:
        """Abort the scan (if any) and halt every axis with X-rays off; takes no lock, never queues."""
        active = self.current
        if active is not None:
            active.runner.abort(reason)
        if self.bench is None or self._loop is None or not self._loop.is_running():
            return (active.scan_id if active else None), None
        bench = self.bench
        return (active.scan_id if active else None), asyncio.run_coroutine_threadsafe(bench.stop_all(), self._loop)
