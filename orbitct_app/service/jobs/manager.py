"""Calibration and reconstruction jobs, each in its own worker process; progress and logs flow back to the DB and the event bus."""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import threading
import time
import traceback
import uuid
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from orbitct.progress import ProgressEvent
from orbitct_app.service.core.children import die_with_parent
from orbitct_app.service.core.db import Store, utc_now
from orbitct_app.service.core.events import EventBus
from orbitct_app.service.jobs.tasks import run_calibration, run_reconstruction

log = logging.getLogger("orbitct.service.jobs")

# kind -> what a worker runs: f(scan_path, params, out_dir, progress) -> result dict (picklable by reference)
JOB_TARGETS: dict[str, Callable[..., dict[str, Any]]] = {
    "calibration": run_calibration,
    "reconstruction": run_reconstruction,
}
_CTX = mp.get_context("spawn")
JOB_NICE = 5


class JobCancelled(Exception):
    """Raised inside a worker when its job was cancelled."""


# ------------------------------------------------------------------ worker side
class _PipeLogHandler(logging.Handler):
    def __init__(self, conn: Connection) -> None:
        super().__init__(level=logging.INFO)
        self._conn = conn

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self._conn.send(("log", f"{record.levelname.lower()}: {record.getMessage()}"))
        except Exception:  # noqa: BLE001 - a log line must never break the job
            pass


def _worker_main(func: Callable[..., dict[str, Any]], scan_path: str, params: dict[str, Any], out_dir: str,
                 conn: Connection, cancel: Any, parent_pid: int) -> None:
    """Entry point of a job process: run ``target`` and send progress, log lines and the outcome over ``conn``;
    killed with the service."""
    die_with_parent(parent_pid)
    try:
        os.nice(JOB_NICE)  # batch work: never take CPU from a running acquisition
    except OSError:
        pass
    logging.basicConfig(level=logging.WARNING)
    logging.getLogger().addHandler(_PipeLogHandler(conn))
    logging.getLogger().setLevel(logging.INFO)
    logging.captureWarnings(True)
    warnings.simplefilter("default")
    last_stage = [""]

    def progress(event: ProgressEvent) -> None:
        if cancel.is_set():
            raise JobCancelled("cancelled on request")
        conn.send(("progress", {
            "stage": event.stage, "done": int(event.done), "total": int(event.total),
            "message": event.message, "metrics": {k: float(v) for k, v in dict(event.metrics).items()},
        }))
        if event.stage != last_stage[0]:
            last_stage[0] = event.stage
            conn.send(("log", f"stage {event.stage}: {event.message}".rstrip(": ")))

    try:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        result = func(Path(scan_path), params, Path(out_dir), progress)
        conn.send(("result", result))
    except JobCancelled as exc:
        conn.send(("cancelled", str(exc)))
    except BaseException as exc:  # noqa: BLE001 - every failure becomes a message to the parent
        conn.send(("log", "error: " + "".join(traceback.format_exception_only(type(exc), exc)).strip()))
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


# ------------------------------------------------------------------ service side
@dataclass
class _Running:
    job_id: str
    scan_id: str
    process: Any
    conn: Connection
    cancel: Any
    cancel_at: float | None = None
    outcome: tuple[str, str, dict[str, Any]] | None = None


class JobManager:
    """Queue of jobs; runs up to ``workers`` at once, never two on the same scan file."""

    def __init__(self, store: Store, bus: EventBus, data_dir: Path, *, workers: int = 1, cancel_grace_s: float = 5.0,
                 scan_busy: Callable[[str], bool] | None = None) -> None:
        self._store, self._bus = store, bus
        self._data_dir = Path(data_dir).resolve()
        self._workers, self._grace = workers, cancel_grace_s
        self._scan_busy = scan_busy or (lambda scan_id: False)
        self._running: dict[str, _Running] = {}
        self._lock = threading.Lock()
        self._queue_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()  # no new launches
        self._exit = threading.Event()  # the dispatcher ends
        self._thread = threading.Thread(target=self._loop, name="orbitct-jobs", daemon=True)

    def start(self) -> None:
        """Start the dispatcher thread."""
        self._thread.start()

    def job_dir(self, job_id: str) -> Path:
        """Output folder of a job (report plots, slices, exports)."""
        return self._data_dir / "jobs" / job_id

    def submit(self, kind: str, scan_id: str, params: dict[str, Any], owner: str) -> str:
        """Queue a job; returns its id."""
        if kind not in JOB_TARGETS:
            raise ValueError(f"job kind must be one of {sorted(JOB_TARGETS)}, got {kind!r}")
        job_id = uuid.uuid4().hex[:16]
        self._store.add_job(job_id, kind=kind, scan_id=scan_id, params=params, owner=owner)
        self._bus.publish(f"job:{job_id}", "state", {"state": "queued", "reason": ""})
        self._wake.set()
        return job_id

    def busy_scans(self) -> set[str]:
        """Scans a job is working on now."""
        with self._lock:
            return {r.scan_id for r in self._running.values()}

    def cancel(self, job_id: str, reason: str = "cancelled on request") -> str:
        """Cancel a queued or running job; returns the state it is now in."""
        with self._queue_lock:  # the dispatcher cannot start it meanwhile
            with self._lock:
                running = self._running.get(job_id)
                if running is not None:
                    running.cancel.set()
                    running.cancel_at = running.cancel_at or time.monotonic()
                    self._wake.set()
                    return "cancelling"
            job = self._store.get_job(job_id)
            if job is not None and job["state"] == "queued":
                self._finish(job_id, "cancelled", reason, {})
                return "cancelled"
        return job["state"] if job is not None else "unknown"

    def shutdown(self, reason: str = "service stopped while the job was running") -> None:
        """Stop the dispatcher; running jobs are terminated and marked interrupted.

        The workers are ended before the dispatcher thread: they were started from it and die with it
        (parent-death signal), so it outlives their grace period.
        """
        self._stop.set()  # nothing new is launched
        with self._queue_lock, self._lock:
            running = list(self._running.values())
            self._running.clear()
        for r in running:
            r.cancel.set()
            r.process.join(timeout=min(self._grace, 2.0))
            if r.process.is_alive():
                r.process.kill()
                r.process.join(timeout=5.0)
            self._finish(r.job_id, "interrupted", reason, {})
        self._exit.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10.0)

    # ------------------------------------------------------------ internals
    def _loop(self) -> None:
        while not self._exit.is_set():
            try:
                self._start_queued()
                self._poll_running()
            except Exception:  # noqa: BLE001 - the dispatcher must survive anything
                log.exception("job dispatcher error")
            self._wake.wait(0.05)
            self._wake.clear()

    def _start_queued(self) -> None:
        with self._queue_lock:
            self._start_queued_locked()

    def _start_queued_locked(self) -> None:
        if self._stop.is_set():
            return
        with self._lock:
            free = self._workers - len(self._running)
            busy = {r.scan_id for r in self._running.values()}
        if free <= 0:
            return
        for job in self._store.queued_jobs():
            if free <= 0:
                break
            if job["scan_id"] in busy or self._scan_busy(job["scan_id"]):
                continue
            scan = self._store.get_scan(job["scan_id"])
            if scan is None or scan["state"] != "complete":
                state = scan["state"] if scan else "missing"
                self._finish(job["id"], "failed", f"scan {job['scan_id']} is {state}, jobs need a complete scan", {})
                continue
            self._launch(job, self._data_dir / scan["file"])
            busy.add(job["scan_id"])
            free -= 1

    def _launch(self, job: dict[str, Any], scan_path: Path) -> None:
        parent, child = _CTX.Pipe(duplex=False)
        cancel = _CTX.Event()
        out_dir = self.job_dir(job["id"])
        proc = _CTX.Process(
            target=_worker_main, name=f"orbitct-job-{job['id']}", daemon=True,
            args=(JOB_TARGETS[job["kind"]], str(scan_path), job["params"], str(out_dir), child, cancel, os.getpid()),
        )
        self._store.update_job(job["id"], state="running", started_utc=utc_now())
        self._bus.publish(f"job:{job['id']}", "state", {"state": "running", "reason": ""})
        proc.start()
        child.close()
        with self._lock:
            self._running[job["id"]] = _Running(job["id"], job["scan_id"], proc, parent, cancel)
        self._store.add_log(job["id"], [f"started {job['kind']} on scan {job['scan_id']} (pid {proc.pid})"])

    def _poll_running(self) -> None:
        with self._lock:
            running = list(self._running.values())
        for r in running:
            self._drain(r)
            if r.cancel_at is not None and r.process.is_alive() and time.monotonic() - r.cancel_at > self._grace:
                r.process.kill()
                r.outcome = ("cancelled", "cancelled on request (worker killed after the grace period)", {})
            if not r.process.is_alive():
                r.process.join(timeout=1.0)
                self._drain(r)
                state, reason, result = r.outcome or (
                    ("cancelled", "cancelled on request", {}) if r.cancel.is_set()
                    else ("failed", f"worker process ended without a result (exit code {r.process.exitcode})", {})
                )
                with self._lock:
                    self._running.pop(r.job_id, None)
                self._finish(r.job_id, state, reason, result)
                self._wake.set()

    def _drain(self, r: _Running) -> None:
        progress: dict[str, Any] | None = None
        lines: list[str] = []
        try:
            while r.conn.poll():
                kind, payload = r.conn.recv()
                if kind == "progress":
                    payload["message"] = self._scrub(str(payload.get("message", "")))[:500]
                    progress = payload
                    self._bus.publish(f"job:{r.job_id}", "progress", payload)
                elif kind == "log":
                    lines.append(self._scrub(str(payload)))
                elif kind == "result":
                    r.outcome = ("succeeded", "", payload)
                elif kind == "cancelled":
                    r.outcome = ("cancelled", "cancelled on request", {})
                elif kind == "error":
                    r.outcome = ("failed", self._scrub(str(payload))[:1000], {})
        except (EOFError, OSError):
            pass
        if progress is not None:
            self._store.update_job(r.job_id, progress=progress)
        if lines:
            self._store.add_log(r.job_id, lines)

    def _scrub(self, text: str) -> str:
        """Hide the service's own paths in messages shown to clients."""
        return text.replace(str(self._data_dir) + os.sep, "").replace(str(self._data_dir), "<data>")

    def _finish(self, job_id: str, state: str, reason: str, result: dict[str, Any]) -> None:
        self._store.update_job(job_id, state=state, reason=reason, result=json.loads(json.dumps(result, default=str)),
                               finished_utc=utc_now())
        self._store.add_log(job_id, [f"{state}" + (f": {reason}" if reason else "")])
        self._bus.publish(f"job:{job_id}", "state", {"state": state, "reason": reason})
        self._bus.publish(f"job:{job_id}", "end", {"state": state, "reason": reason})
