"""The web server's handle on the bench process: commands, scan progress snapshots, emergency stop.

The devices and the acquisition loop live in their own process (``benchproc``), so no request
can take the scan's interpreter lock or CPU time slice. Status reads come from an in-memory
snapshot kept up to date by a reader thread; the emergency stop goes down its own pipe.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import itertools
import logging
import multiprocessing as mp
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from acquire.rigs.links import DeviceLink
from orbitct_app.service.core.children import Backoff
from orbitct_app.service.core.db import Store, utc_now
from orbitct_app.service.core.errors import (
    ApiError,
    Conflict,
    InsufficientStorage,
    Internal,
    Invalid,
    NotFound,
    StopLatched,
    Unavailable,
)
from orbitct_app.service.core.events import EventBus
from orbitct_app.service.core.files import summarize_scan
from orbitct_app.service.rig import SERVICE_STOPPED

log = logging.getLogger("orbitct.service.rig")
_CTX = mp.get_context("spawn")
ERROR_KINDS: dict[str, type[ApiError]] = {
    "invalid": Invalid,
    "conflict": Conflict,
    "stop_latched": StopLatched,
    "not_found": NotFound,
    "unavailable": Unavailable,
    "error": Internal,
    "insufficient_storage": InsufficientStorage,
}


@dataclass
class ActiveScan:
    """The scan on the bench now, with its latest progress (read without locks)."""

    scan_id: str
    path: Path
    progress: dict[str, Any] = field(default_factory=dict)
    state: str = "running"
    expected_s: float | None = None  # how long its frames take in all, once the scan has said so
    last_db: float = 0.0
    done: threading.Event = field(default_factory=threading.Event)


class RigClient:
    """Starts the rig process and relays commands, progress and the emergency stop."""

    def __init__(
        self,
        config_path: Path,
        *,
        sim: bool,
        store: Store,
        bus: EventBus,
        data_dir: Path,
        status_interval_s: float = 0.25,
        nice: int = 0,
        latch_flag: Any = None,
    ) -> None:
        self.config_path = Path(config_path)
        self.sim, self.nice = sim, nice
        self.latch_flag = latch_flag
        self.links: dict[str, Any] | None = None
        self._store, self._bus = store, bus
        self._data_dir = Path(data_dir)
        self._interval = status_interval_s
        self.connection_state = "not started"
        self.current: ActiveScan | None = None
        self._ids = itertools.count(1)
        self._pending: dict[int, concurrent.futures.Future[Any]] = {}
        self._start_lock = threading.Lock()
        self._cmd_lock = threading.Lock()
        self._stop_lock = threading.Lock()
        self._connected = threading.Event()
        self._process: Any = None
        self._cmd: Any = None
        self._stop: Any = None
        self._events: Any = None
        self._reader: threading.Thread | None = None
        self._db = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="orbitct-scan-db")
        self._closing = False
        self._backoff = Backoff()
        self._started_at = 0.0

    # ------------------------------------------------------------ lifecycle
    def start(self, links: Mapping[str, DeviceLink] | None = None, timeout_s: float = 120.0) -> None:
        """Start the rig process and wait until it has connected every device (at ``links``, else as configured)."""
        if links is not None:
            self.links = {k: (v.uri, dict(v.options)) for k, v in links.items()}
        self._spawn(timeout_s)

    def _spawn(self, timeout_s: float = 120.0) -> None:
        from orbitct_app.service.rig.process import rig_main

        self._connected.clear()
        cmd_parent, cmd_child = _CTX.Pipe()
        stop_parent, stop_child = _CTX.Pipe()
        events_parent, events_child = _CTX.Pipe(duplex=False)
        self._cmd, self._stop, self._events = cmd_parent, stop_parent, events_parent
        self.connection_state = "connecting"
        self._process = _CTX.Process(
            target=rig_main,
            name="orbitct-rig",
            daemon=True,
            args=(
                str(self.config_path),
                self.sim,
                cmd_child,
                stop_child,
                events_child,
                self.nice,
                self.links,
                str(self._data_dir),
                self.latch_flag,
            ),
        )
        self._process.start()
        self._started_at = time.monotonic()
        for conn in (cmd_child, stop_child, events_child):
            conn.close()
        self._reader = threading.Thread(target=self._read, name="orbitct-rig-events", daemon=True)
        self._reader.start()
        if not self._connected.wait(timeout_s):
            self.connection_state = f"failed: the bench did not connect within {timeout_s:g} s"
        if self.connection_state != "connected":
            log.error("bench: %s", self.connection_state)

    def close(self, reason: str = f"{SERVICE_STOPPED} (shut down)") -> None:
        """Abort a running scan, halt everything, stop the bench process."""
        self._closing = True
        if self._process is not None and self._process.is_alive() and self.connection_state == "connected":
            try:
                self.command("shutdown", timeout_s=10.0, reason=reason)
            except ApiError:
                pass
            self._process.join(30.0)
        if self._process is not None and self._process.is_alive():
            self._process.kill()
            self._process.join(5.0)
        for conn in (self._cmd, self._stop):
            if conn is not None:
                conn.close()
        if self._reader is not None:
            self._reader.join(5.0)
        self._db.shutdown(wait=True)
        self.connection_state = "closed"

    # ------------------------------------------------------------ messages from the bench process
    def _read(self) -> None:
        while True:
            try:
                message = self._events.recv()
            except (EOFError, OSError):
                break
            try:
                self._dispatch(message)
            except Exception:  # the reader must survive anything
                log.exception("bench message %r", message[:2])
        self._bench_gone()

    def _dispatch(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "reply":
            _, req_id, ok, payload = message
            fut = self._pending.pop(req_id, None)
            if fut is not None and not fut.done():
                if ok:
                    fut.set_result(payload)
                else:
                    err_kind, text = payload
                    fut.set_exception(ERROR_KINDS.get(err_kind, Unavailable)(text))
        elif kind == "progress":
            self._on_progress(message[1], message[2])
        elif kind == "scan_end":
            self._on_scan_end(*message[1:])
        elif kind == "scan_warning":
            self._bus.publish(f"scan:{message[1]}", "warning", message[2])
        elif kind == "scan_calibration":
            self._bus.publish(f"scan:{message[1]}", "calibration", message[2])
        elif kind == "connected":
            self.connection_state = "connected"
            self._connected.set()
        elif kind == "connect_failed":
            self.connection_state = f"failed: {message[1]}"
            self._connected.set()

    def _bench_gone(self) -> None:
        """The rig process ended: fail what waits on it, close the scan record, start it again (unless closing)."""
        if self.connection_state in ("connected", "connecting") or not self.connection_state.startswith("failed"):
            self.connection_state = "failed: the bench process ended"
        self._connected.set()
        for fut in list(self._pending.values()):
            if not fut.done():
                fut.set_exception(Unavailable(f"the bench is not available ({self.connection_state})"))
        self._pending.clear()
        active = self.current
        if active is not None:
            summary: dict[str, Any] = {}
            if active.path.exists():
                self._repair_after_exit(active.path)
                summary = summarize_scan(active.path)
            self._on_scan_end(active.scan_id, "failed", "the bench process ended during the scan", summary)
        if not self._closing:
            threading.Thread(target=self._restart, name="orbitct-rig-restart", daemon=True).start()

    def _restart(self) -> None:
        """Start the rig process again after a crash, backing off while it keeps failing; never gives up."""
        if self._process is not None:
            self._process.join(10.0)
        delay = self._backoff.delay(time.monotonic() - self._started_at)
        why = self.connection_state.split("; restart")[0]
        self.connection_state = f"{why}; restarting the rig process (restart {self._backoff.restarts} in {delay:g} s)"
        log.error("bench: %s", self.connection_state)
        time.sleep(delay)
        if self._closing:
            return
        self.connection_state = "connecting"
        for conn in (self._cmd, self._stop):
            if conn is not None:
                conn.close()
        self._spawn()

    def _repair_after_exit(self, path: Path) -> None:
        """Mark the scan file of a dead bench aborted, once the process has let go of it."""
        from acquire.repair import repair_scan

        # The pipe can report EOF before the dying process has closed the HDF5 file (and its lock).
        if self._process is not None:
            self._process.join(10.0)
        deadline = time.monotonic() + 10.0
        while True:
            try:
                repair_scan(path)  # keep every written frame, mark the file aborted
                return
            except Exception as exc:  # noqa: BLE001
                if time.monotonic() > deadline:
                    log.error("could not repair %s: %s", path.name, exc)
                    return
                time.sleep(0.2)

    # ------------------------------------------------------------ commands
    def submit(self, name: str, /, **args: Any) -> concurrent.futures.Future[Any]:
        """Send a command to the bench process; the future holds its reply."""
        if self.connection_state != "connected" or self._cmd is None:
            raise Unavailable(f"the bench is not connected ({self.connection_state})")
        req_id = next(self._ids)
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        self._pending[req_id] = fut
        try:
            with self._cmd_lock:
                self._cmd.send((req_id, name, args))
        except (OSError, ValueError) as exc:
            self._pending.pop(req_id, None)
            raise Unavailable(f"the bench is not reachable ({exc})") from None
        return fut

    def command(self, name: str, /, *, timeout_s: float = 30.0, **args: Any) -> Any:
        """Run a command and wait for its reply (from a worker thread)."""
        fut = self.submit(name, **args)
        try:
            return fut.result(timeout_s)
        except concurrent.futures.TimeoutError:
            raise Unavailable(f"the bench did not answer {name!r} within {timeout_s:g} s") from None

    async def run(self, name: str, /, *, timeout_s: float = 30.0, **args: Any) -> Any:
        """Run a command and await its reply (from the web server's loop)."""
        fut = self.submit(name, **args)
        try:
            return await asyncio.wait_for(asyncio.wrap_future(fut), timeout_s)
        except TimeoutError:
            raise Unavailable(f"the bench did not answer {name!r} within {timeout_s:g} s") from None

    # ------------------------------------------------------------ scans
    @property
    def busy(self) -> str | None:
        """Id of the scan on the bench, if any."""
        active = self.current
        return active.scan_id if active is not None else None

    def preflight(self, spec: dict[str, Any]) -> None:
        """Check a scan against every limit before anything moves (``Invalid`` names the frame and axis)."""
        self.command("preflight", timeout_s=120.0, spec=spec)

    def start_scan(self, scan_id: str, spec: dict[str, Any]) -> ActiveScan:
        """Start a scan; 409 if one is running."""
        with self._start_lock:
            if self.current is not None:
                raise Conflict(
                    f"the bench is busy with scan {self.current.scan_id}", advice="start this one when it has ended"
                )
            active = ActiveScan(scan_id, Path(spec["out"]))
            self.current = active
        try:
            self._store.update_scan(scan_id, state="running", started_utc=utc_now())
            self._set_state(active, "running", "")
            self.command("start_scan", scan_id=scan_id, spec=spec)
        except Exception:
            self.current = None
            raise
        return active

    def _set_state(self, active: ActiveScan, state: str, reason: str) -> None:
        active.state = state
        self._bus.publish(f"scan:{active.scan_id}", "state", {"state": state, "reason": reason})

    def _on_progress(self, scan_id: str, data: dict[str, Any]) -> None:
        active = self.current
        if active is None or active.scan_id != scan_id:
            return
        if data["stage"] == "duration":  # said once: kept with every later progress of the scan
            active.expected_s = float(data["metrics"]["expected_s"])
            active.progress = {**active.progress, "expected_s": active.expected_s}
            self._bus.publish(f"scan:{scan_id}", "progress", data)
            return
        if active.expected_s is not None:
            data = {**data, "expected_s": active.expected_s}
        active.progress = data
        if data["message"] == "paused" and active.state != "paused":
            self._set_state(active, "paused", "")
        elif active.state == "paused" and data["message"] != "paused" and data["stage"] == "scan":
            self._set_state(active, "running", "")
        self._bus.publish(f"scan:{scan_id}", "progress", data)
        now = time.monotonic()
        if now - active.last_db >= self._interval:
            active.last_db = now
            self._db.submit(
                self._store.update_scan, scan_id, frames_done=data["done"], frames_total=data["total"], progress=data
            )

    def _on_scan_end(self, scan_id: str, state: str, reason: str, summary: dict[str, Any]) -> None:
        reason = reason.replace(str(self._data_dir.resolve()) + "/", "").replace(str(self._data_dir) + "/", "")
        active = self.current
        progress = active.progress if active is not None and active.scan_id == scan_id else {}
        fields: dict[str, Any] = dict(
            state=state,
            reason=reason[:2000],
            finished_utc=utc_now(),
            summary=summary,
            progress=progress,
            frames_done=int(summary.get("n_frames", progress.get("done", 0))),
        )
        if progress.get("total"):
            fields["frames_total"] = int(progress["total"])
        try:  # a record that cannot be written now is kept by the store and written later; never a reason to hang
            self._db.submit(self._store.update_scan, scan_id, **fields).result(30.0)
        except Exception as exc:  # noqa: BLE001 - the scan has ended whatever its record says
            log.error("scan %s ended (%s) but its record could not be written: %s", scan_id, state, exc)
        finally:
            if active is not None and active.scan_id == scan_id:
                self.current = None  # the bench takes the next scan
                active.done.set()
                with contextlib.suppress(Exception):
                    self._set_state(active, state, reason)
            with contextlib.suppress(Exception):
                self._bus.publish(f"scan:{scan_id}", "end", {"state": state, "reason": reason})

    def pause(self, scan_id: str) -> None:
        """Pause the running scan at the next frame boundary."""
        self._active(scan_id)
        self.command("pause", scan_id=scan_id)

    def resume(self, scan_id: str) -> None:
        """Resume a paused scan."""
        active = self._active(scan_id)
        self.command("resume", scan_id=scan_id)
        if active.state == "paused":
            self._set_state(active, "running", "")

    def abort(self, scan_id: str, reason: str) -> None:
        """Abort the running scan (halt, X-rays off, file marked aborted)."""
        self._active(scan_id)
        self.command("abort", scan_id=scan_id, reason=reason)

    def _active(self, scan_id: str) -> ActiveScan:
        active = self.current
        if active is None or active.scan_id != scan_id:
            raise Conflict(f"scan {scan_id} is not running on the bench")
        return active

    # ------------------------------------------------------------ emergency stop
    def emergency_stop(self, reason: str) -> tuple[str | None, concurrent.futures.Future[Any] | None]:
        """Abort the scan and halt every axis with X-rays off, down the stop pipe; never queues behind a command."""
        active = self.current
        scan_id = active.scan_id if active is not None else None
        if self.connection_state != "connected" or self._stop is None:
            return scan_id, None
        req_id = next(self._ids)
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        self._pending[req_id] = fut
        try:
            with self._stop_lock:
                self._stop.send((req_id, reason))
        except (OSError, ValueError):
            self._pending.pop(req_id, None)
            return scan_id, None
        return scan_id, fut
