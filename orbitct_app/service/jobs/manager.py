"""Calibration and reconstruction jobs on a Dask cluster (``dask.distributed``): an embedded local cluster of worker
processes by default, or an existing scheduler given by address. Progress, log lines and the outcome flow back to
the DB and the event bus; a cancel is asked of the job at its next progress event, and its worker is restarted when
it does not stop within the grace period."""

from __future__ import annotations

import json
import logging
import os
import queue
import threading
import time
import uuid
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from acquire.priority import JOB_NICE
from orbitct.progress import ProgressEvent
from orbitct_app.error_codes import code_for_exception
from orbitct_app.service.core.db import Store, utc_now
from orbitct_app.service.core.events import EventBus
from orbitct_app.service.core.failures import failure_sentence
from orbitct_app.service.jobs.tasks import run_calibration, run_reconstruction

log = logging.getLogger("orbitct.service.jobs")

# kind -> what a worker runs: f(scan_path, params, out_dir, progress) -> result dict (picklable by reference)
JOB_TARGETS: dict[str, Callable[..., dict[str, Any]]] = {
    "calibration": run_calibration,
    "reconstruction": run_reconstruction,
}
TOPIC = "orbitct-jobs"  # the Dask event topic jobs report on
CANCEL_CHECK_S = 0.2  # how often a job asks whether it was cancelled (at its progress events)
WORKER_CHECK_S = 1.0  # how often the service looks whether the workers running jobs are still there


class JobCancelled(Exception):
    """Raised inside a worker when its job was cancelled."""


class JobEngineError(RuntimeError):
    """The Dask cluster cannot be started or reached."""


# ------------------------------------------------------------------ worker side
class _EventLogHandler(logging.Handler):
    def __init__(self, send: Callable[[str, Any], None]) -> None:
        super().__init__(level=logging.INFO)
        self._send = send

    def emit(self, record: logging.LogRecord) -> None:
        if not getattr(record, "job_log", True):  # for the worker's own log only (a traceback)
            return
        try:
            self._send("log", f"{record.levelname.lower()}: {record.getMessage()}")
        except Exception:  # noqa: BLE001 - a log line must never break the job
            pass


def _exit_with(owner_pid: int) -> None:
    """Thread of an embedded cluster's worker: end the process once the service that owns it is gone (a job
    must not write into a scan file whose record says it never did)."""
    import psutil

    while psutil.pid_exists(owner_pid):
        time.sleep(0.5)
    os._exit(1)


def run_job(
    func: Callable[..., dict[str, Any]],
    job_id: str,
    scan_path: str,
    params: dict[str, Any],
    out_dir: str,
    owner_pid: int | None = None,
) -> dict[str, Any]:
    """What a Dask worker runs for one job: ``func`` with a progress callback that reports on :data:`TOPIC` and
    raises :class:`JobCancelled` once the job's cancel event is set. Returns the result, or the outcome
    ``{"cancelled": reason}`` / ``{"error": message}``, with ``events``, the number of events sent before it.
    ``owner_pid``: on an embedded cluster, the service's process; the worker ends when it is gone."""
    from distributed import Event, get_worker

    worker = get_worker()
    if owner_pid is not None and not getattr(worker, "_orbitct_owner_watch", False):
        threading.Thread(target=_exit_with, args=(owner_pid,), name="orbitct-owner-watch", daemon=True).start()
        worker._orbitct_owner_watch = True  # type: ignore[attr-defined]
    if not getattr(worker, "_orbitct_niced", False):
        try:
            os.nice(JOB_NICE)  # batch work: never take CPU from a running acquisition
        except OSError:
            pass
        worker._orbitct_niced = True  # type: ignore[attr-defined]
        logging.captureWarnings(True)  # a job's Python warnings go to its log like its log lines
        if logging.getLogger().level > logging.INFO:
            logging.getLogger().setLevel(logging.INFO)  # as before Dask: a job's info lines reach its log
    sent = [0]
    cancel = Event(f"orbitct-cancel-{job_id}")
    checked = [0.0]
    last_stage = [""]

    def send(kind: str, payload: Any) -> None:
        sent[0] += 1
        worker.log_event(TOPIC, {"job": job_id, "seq": sent[0], "kind": kind, "payload": payload})

    def progress(event: ProgressEvent) -> None:
        now = time.monotonic()
        if now - checked[0] > CANCEL_CHECK_S:
            checked[0] = now
            if cancel.is_set():
                raise JobCancelled("cancelled on request")
        send(
            "progress",
            {
                "stage": event.stage,
                "done": int(event.done),
                "total": int(event.total),
                "message": event.message,
                "metrics": {k: float(v) for k, v in dict(event.metrics).items()},
            },
        )
        if event.stage != last_stage[0]:
            last_stage[0] = event.stage
            send("log", f"stage {event.stage}: {event.message}".rstrip(": "))

    handler = _EventLogHandler(send)
    thread = threading.get_ident()
    handler.addFilter(lambda record: record.thread == thread)  # this job's lines, not the worker's other threads'
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            Path(out_dir).mkdir(parents=True, exist_ok=True)
            send("started", {"worker": worker.address, "pid": os.getpid()})
            send("log", f"running on the Dask worker {worker.address} (pid {os.getpid()})")
            result = func(Path(scan_path), params, Path(out_dir), progress)
        return {"result": result, "events": sent[0]}
    except JobCancelled as exc:
        return {"cancelled": str(exc), "events": sent[0]}
    except Exception as exc:  # every failure becomes the job's reason
        log.error("job %s failed", job_id, exc_info=True, extra={"job_log": False})  # details for the worker's log
        text = failure_sentence(exc)
        code = code_for_exception(exc)
        send("log", f"error [{code}]: {text}")
        return {"error": text, "code": code, "events": sent[0]}
    finally:
        root.removeHandler(handler)


def _judged(result: dict[str, Any]) -> tuple[str, str, dict[str, Any]]:
    """A finished job's state by its result's verdict: a failed quality check fails the job, result kept."""
    verdict = result.get("verdict") or {}
    if verdict.get("status") != "failed":
        return "succeeded", "", result
    reasons = "; ".join(verdict.get("reasons") or ["no reason given"])
    return (
        "failed",
        f"the quality check failed: {reasons}. The result is kept, marked failed; see 'When a calibration fails its "
        "quality check' in the documentation",
        result,
    )


# ------------------------------------------------------------------ service side
@dataclass
class _Running:
    job_id: str
    scan_id: str
    future: Any
    cancel: Any  # distributed.Event
    cancel_at: float | None = None
    error_code: str | None = None  # the catalogue's code of a failure, when the outcome knows it
    outcome: tuple[str, str, dict[str, Any]] | None = None
    events_expected: int | None = None
    events_seen: int = 0
    done_at: float | None = None
    progress: dict[str, Any] | None = None
    expected_s: float | None = None  # how long the job takes in all, once it has said so
    lines: list[str] = field(default_factory=list)
    worker: str | None = None  # the Dask worker running it now (from its own word)
    attempts: int = 0  # how often a worker started it
    worker_gone: bool = False  # its worker left the cluster (said once)


class JobManager:
    """Queue of jobs; runs up to ``workers`` at once on the Dask cluster, never two on the same scan file.

    ``scheduler``: the address of an existing Dask scheduler (``tcp://host:8786``); without one an embedded local
    cluster of ``workers`` worker processes starts with the service. The workers must see the data directory at
    the same path."""

    def __init__(
        self,
        store: Store,
        bus: EventBus,
        data_dir: Path,
        *,
        workers: int = 1,
        cancel_grace_s: float = 5.0,
        scan_busy: Callable[[str], bool] | None = None,
        scheduler: str | None = None,
        scheduler_timeout_s: float = 10.0,
    ) -> None:
        """``scheduler_timeout_s``: how long connecting to ``scheduler`` may take."""
        self._store, self._bus = store, bus
        self._data_dir = Path(data_dir).resolve()
        self._workers, self._grace = workers, cancel_grace_s
        self._scan_busy = scan_busy or (lambda scan_id: False)
        self._scheduler, self._scheduler_timeout = scheduler, scheduler_timeout_s
        self._client: Any = None
        self._cluster: Any = None
        self.engine_state = "starting"  # starting | connected | failed: <why> | lost: <why>
        self._running: dict[str, _Running] = {}
        self._workers_checked = 0.0
        self._events: queue.Queue[dict[str, Any]] = queue.Queue()
        self._lock = threading.Lock()
        self._queue_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()  # no new launches
        self._exit = threading.Event()  # the dispatcher ends
        self._thread = threading.Thread(target=self._loop, name="orbitct-jobs", daemon=True)

    def start(self) -> None:
        """Start the dispatcher thread (it connects to the cluster, or starts the embedded one)."""
        self._thread.start()

    @property
    def where(self) -> str:
        """Where jobs run, in words."""
        if self._scheduler:
            return f"the Dask scheduler at {self._scheduler}"
        return f"an embedded Dask cluster of {self._workers} worker process(es)"

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
                    with _quiet():
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
        """Stop the dispatcher; running jobs are cancelled on the cluster and marked interrupted; the embedded
        cluster stops."""
        self._stop.set()  # nothing new is launched
        with self._queue_lock, self._lock:
            running = list(self._running.values())
            self._running.clear()
        for r in running:
            with _quiet():
                r.cancel.set()
            with _quiet():
                r.future.cancel()
            self._finish(r.job_id, "interrupted", reason, {})
        self._exit.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=30.0)

    # ------------------------------------------------------------ the cluster
    def _connect(self) -> None:
        from distributed import Client, LocalCluster

        try:
            if self._scheduler:
                self._client = Client(self._scheduler, timeout=self._scheduler_timeout, set_as_default=False)
            else:
                self._cluster = LocalCluster(
                    n_workers=self._workers,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address="127.0.0.1:0",
                    host="127.0.0.1",
                    memory_limit=0,
                    silence_logs=logging.WARNING,
                )
                self._client = Client(self._cluster, set_as_default=False)
            self._client.subscribe_topic(TOPIC, lambda event: self._events.put(event[1]))
        except Exception as exc:  # noqa: BLE001 - the service runs on, jobs stay queued and say why
            self.engine_state = f"failed: {self.where} could not be reached ({exc or 'no answer'})"
            log.error("job engine: %s", self.engine_state)
            self._close_client()
            return
        self.engine_state = "connected"
        log.info("jobs run on %s", self.where)

    def _close_client(self) -> None:
        if self._client is not None:
            with _quiet():
                self._client.close(timeout=5)
        if self._cluster is not None:
            with _quiet():
                self._cluster.close()
        self._client = self._cluster = None

    def _engine_lost(self) -> bool:
        """Whether the client is out of touch with the scheduler (it keeps trying to reconnect); running jobs then
        fail with the reason (their futures are gone) and queued ones wait."""
        status = getattr(self._client, "status", "closed")
        if status == "running":
            if self.engine_state.startswith("lost"):
                self.engine_state = "connected"
                log.warning("job engine: %s is back", self.where)
            return False
        if not self.engine_state.startswith("lost"):
            self.engine_state = f"lost: {self.where} went away (client {status})"
            log.error("job engine: %s", self.engine_state)
        return True

    # ------------------------------------------------------------ internals
    def _loop(self) -> None:
        self._connect()
        try:
            while not self._exit.is_set():
                try:
                    self._dispatch_events()
                    if self._client is not None:
                        lost = self._engine_lost()
                        if not lost:
                            self._start_queued()
                        self._poll_running(lost)
                except Exception:  # the dispatcher must survive anything
                    log.exception("job dispatcher error")
                self._wake.wait(0.05)
                self._wake.clear()
        finally:
            self._close_client()

    def _start_queued(self) -> None:
        with self._queue_lock:
            self._start_queued_locked()

    def _start_queued_locked(self) -> None:
        if self._stop.is_set() or self.engine_state != "connected" or self._client.status != "running":
            return  # queued jobs wait for the cluster
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
                self._finish(
                    job["id"], "failed", f"scan {job['scan_id']} is {state}, jobs need a complete scan", {}, "conflict"
                )
                continue
            self._launch(job, self._data_dir / scan["file"])
            busy.add(job["scan_id"])
            free -= 1

    def _launch(self, job: dict[str, Any], scan_path: Path) -> None:
        from distributed import Event

        job_id = job["id"]
        cancel = Event(f"orbitct-cancel-{job_id}", client=self._client)
        cancel.clear()
        future = self._client.submit(
            run_job,
            JOB_TARGETS[job["kind"]],
            job_id,
            str(scan_path),
            job["params"],
            str(self.job_dir(job_id)),
            None if self._scheduler else os.getpid(),
            key=f"orbitct-job-{job_id}",
            pure=False,
        )
        self._store.update_job(job_id, state="running", started_utc=utc_now())
        self._bus.publish(f"job:{job_id}", "state", {"state": "running", "reason": ""})
        with self._lock:
            self._running[job_id] = _Running(job_id, job["scan_id"], future, cancel)
        self._store.add_log(job_id, [f"started {job['kind']} on scan {job['scan_id']} ({self.where})"])

    def _dispatch_events(self) -> None:
        """Progress and log lines the workers sent, to the DB and the bus, in the order each job sent them."""
        while True:
            try:
                msg = self._events.get_nowait()
            except queue.Empty:
                break
            with self._lock:
                r = self._running.get(str(msg.get("job")))
            if r is None:
                continue
            r.events_seen = max(r.events_seen, int(msg.get("seq", 0)))
            if msg["kind"] == "progress":
                payload = dict(msg["payload"])
                payload["message"] = self._scrub(str(payload.get("message", "")))[:500]
                if payload["stage"] == "duration":  # said once: kept with every later progress of the job
                    r.expected_s = float(payload["metrics"]["expected_s"])
                else:
                    if r.expected_s is not None:
                        payload["expected_s"] = r.expected_s
                    r.progress = payload
                self._bus.publish(f"job:{r.job_id}", "progress", payload)
            elif msg["kind"] == "log":
                r.lines.append(self._scrub(str(msg["payload"])))
            elif msg["kind"] == "started":
                self._started(r, str(msg["payload"].get("worker", "")))
        with self._lock:
            running = list(self._running.values())
        for r in running:
            if r.progress is not None:
                self._store.update_job(r.job_id, progress=r.progress)
                r.progress = None
            if r.lines:
                self._store.add_log(r.job_id, r.lines)
                r.lines = []

    def _started(self, r: _Running, worker: str) -> None:
        """A worker started the job: again, when the one before it died (said in its log and events)."""
        r.attempts += 1
        if r.attempts > 1 and not r.worker_gone:  # not said yet by _watch_workers
            self._tell(
                r,
                f"the Dask worker {r.worker} running it died; Dask runs the job again from its start on "
                f"the worker {worker} (attempt {r.attempts})",
            )
        elif r.attempts > 1:
            self._tell(r, f"Dask runs the job again from its start on the worker {worker} (attempt {r.attempts})")
        r.worker, r.worker_gone = worker, False

    def _tell(self, r: _Running, text: str) -> None:
        """One line in the job's log and a ``warning`` event on its stream."""
        r.lines.append("warning: " + text)
        self._bus.publish(f"job:{r.job_id}", "warning", {"message": text})

    def _watch_workers(self, running: list[_Running]) -> None:
        """Say within a second or two when the worker running a job leaves the cluster (killed, out of memory): Dask
        then runs the job again on a live worker, from its start, or fails it after too many deaths."""
        watched = [r for r in running if r.worker and not r.worker_gone and r.outcome is None]
        if not watched or self._client is None or time.monotonic() - self._workers_checked < WORKER_CHECK_S:
            return
        self._workers_checked = time.monotonic()
        try:
            alive = set(self._client.scheduler_info()["workers"])
        except Exception:  # noqa: BLE001 - a client out of touch is handled as a lost engine
            return
        for r in watched:
            if r.worker not in alive:
                r.worker_gone = True  # said once; a second start says it again with the new worker
                self._tell(
                    r,
                    f"the Dask worker {r.worker} running it died (killed, or out of memory); Dask runs the "
                    "job again on a live worker from its start, or fails it if its workers keep dying",
                )

    def _poll_running(self, lost: bool) -> None:
        with self._lock:
            running = list(self._running.values())
        self._watch_workers(running)
        for r in running:
            if r.outcome is None:
                r.outcome = self._outcome(r, lost)
                if r.outcome is not None:
                    r.done_at = time.monotonic()
            if r.outcome is None and r.cancel_at is not None and time.monotonic() - r.cancel_at > self._grace:
                self._restart_worker_of(r)
                r.outcome = ("cancelled", "cancelled on request (its worker was restarted after the grace period)", {})
                r.done_at = time.monotonic()
            if r.outcome is None:
                continue
            # the events a job sent before its result travel apart from it: wait for them (a little)
            if (
                r.events_expected is not None
                and r.events_seen < r.events_expected
                and time.monotonic() - (r.done_at or 0.0) < 2.0
            ):
                continue
            with self._lock:
                self._running.pop(r.job_id, None)
            self._dispatch_events()
            state, reason, result = r.outcome
            self._refresh_summary(r.scan_id)  # before the job says it ended: the scan's record shows its result
            self._finish(r.job_id, state, reason, result, r.error_code)
            self._wake.set()

    def _outcome(self, r: _Running, lost: bool) -> tuple[str, str, dict[str, Any]] | None:
        """The job's final state, reason and result once its future has one (None while it runs)."""
        status = r.future.status
        if status == "finished":
            out = r.future.result()
            r.events_expected = int(out.get("events", 0))
            if "result" in out:
                return _judged(out["result"])
            if "cancelled" in out:
                return "cancelled", str(out["cancelled"]), {}
            r.error_code = str(out.get("code") or "action_failed")
            return "failed", self._scrub(str(out.get("error", "unknown error")))[:1000], {}
        if status == "error":
            exc = r.future.exception()
            name = type(exc).__name__
            if name == "KilledWorker":
                why = (
                    f"the Dask worker running it died, also when the job was run again ({exc}); too little memory, "
                    "or the worker was killed"
                )
            else:
                why = failure_sentence(exc)
            return "failed", self._scrub(why)[:1000], {}
        if lost or status in ("cancelled", "lost"):
            if r.cancel_at is not None:
                return "cancelled", "cancelled on request", {}
            r.error_code = "unavailable"
            client_status = getattr(self._client, "status", "closed")
            why = (
                f"{self.where} went away (client {client_status})"
                if client_status != "running"
                else f"{self.where} dropped the job (its future is {status})"
            )
            return "failed", f"{why}; the job's work there is lost: submit it again", {}
        return None

    def _restart_worker_of(self, r: _Running) -> None:
        """A cancelled job that did not stop: its worker process is restarted (Dask's nanny starts a fresh one)."""
        with _quiet():
            key = r.future.key
            where = [w for w, keys in self._client.processing().items() if key in keys]
            r.future.cancel()
            if where:
                self._client.restart_workers(where, timeout=30)

    def _scrub(self, text: str) -> str:
        """Hide the service's own paths in messages shown to clients."""
        return text.replace(str(self._data_dir) + os.sep, "").replace(str(self._data_dir), "<data>")

    def _refresh_summary(self, scan_id: str) -> None:
        """Summarize the scan file again: a job has written its geometry or volume into it."""
        from orbitct_app.service.core.files import summarize_scan

        with _quiet():
            scan = self._store.get_scan(scan_id)
            if scan is not None:
                summary = summarize_scan(self._data_dir / scan["file"])
                if "error" not in summary:
                    self._store.update_scan(scan_id, summary=summary)

    def _finish(self, job_id: str, state: str, reason: str, result: dict[str, Any], error: str | None = None) -> None:
        """Record the job's end: its state, reason, result and, for a failure or an interruption, the catalogue's
        code (``error``, else the state's: a failed quality check, a failed action, an interruption)."""
        if error is None:
            quality_failed = ((result.get("verdict") or {}).get("status")) == "failed"
            error = {
                "failed": "failed_quality_check" if quality_failed else "action_failed",
                "interrupted": "interrupted",
            }.get(state, "")
        self._store.update_job(
            job_id,
            state=state,
            error=error if state in ("failed", "interrupted") else "",
            reason=reason,
            result=json.loads(json.dumps(result, default=str)),
            finished_utc=utc_now(),
        )
        self._store.add_log(job_id, [f"{state}" + (f": {reason}" if reason else "")])
        self._bus.publish(f"job:{job_id}", "state", {"state": state, "reason": reason})
        self._bus.publish(f"job:{job_id}", "end", {"state": state, "reason": reason})


class _quiet:
    """A block whose errors are logged, not raised (talking to a cluster that may be gone)."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, t: Any, e: BaseException | None, tb: Any) -> bool:
        if e is not None:
            log.debug("job engine: %s", e)
        return True
