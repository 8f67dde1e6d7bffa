"""BB plans made in the background: one at a time, each in a process of its own (spawned, at the jobs' lower
priority), so a plan of minutes neither holds a request open nor competes with the service's own threads.

A plan's state lives beside it under ``<data>/plans``: ``<id>.state`` (JSON: planning with how far it got, failed or
cancelled, with what was asked and why it ended) until the finished plan's ``<id>.json`` and ``<id>.png`` are there; both are
moved into place whole, so a reader never sees half a plan."""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing as mp
import os
import shutil
import signal
import threading
import time
import traceback
import uuid
from collections import deque
from pathlib import Path
from typing import Any

from acquire.priority import JOB_NICE
from orbitct.progress import ProgressEvent
from orbitct_app.bbplan import BBPlanError, BBPlanRequest, make_bb_plan, write_bb_plan
from orbitct_app.service.core.children import die_with_parent
from orbitct_app.service.core.db import utc_now
from orbitct_app.service.core.failures import failure_sentence
from orbitct_app.service.core.jsonfile import write_json_atomically

log = logging.getLogger("orbitct.service.plans")

PLANNING, DONE, FAILED, CANCELLED = "planning", "done", "failed", "cancelled"
#: plans that may wait or run at once; one more is refused (each takes a core for seconds to minutes)
MAX_PLANS_WAITING = 4
STOPPED_REASON = "the service stopped while the plan was being made"
PROGRESS_EVERY_S = 0.5  # a plan's record says how far it got at most this often
_STATE_SUFFIX = ".state"


def plan_path(folder: Path, plan_id: str) -> Path:
    """Where a plan's JSON lies once it is done (its picture beside it, ``.png``)."""
    return folder / f"{plan_id}.json"


class PlansBusy(RuntimeError):
    """As many plans as :data:`MAX_PLANS_WAITING` are already waiting or being made."""


class PlanEnded(RuntimeError):
    """The plan to cancel has already ended."""


def _make_plan(request: BBPlanRequest, folder: str, plan_id: str, parent_pid: int, conn: Any) -> None:
    """In the plan's own process: make the plan, move its JSON and picture into place; send ``("progress", {...})``
    now and then, and last ``("end", None)`` or ``("end", reason)``."""
    die_with_parent(parent_pid)
    for sig in (signal.SIGINT, signal.SIGHUP):  # Ctrl-C at the service's terminal: the service ends the plan
        signal.signal(sig, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.nice(JOB_NICE)
    sent = [0.0]

    def progress(event: ProgressEvent) -> None:
        if event.stage == "duration":  # sent at once: the plan's record keeps it
            conn.send(("progress", {"stage": "duration", "expected_s": float(event.metrics["expected_s"])}))
        elif time.monotonic() - sent[0] >= PROGRESS_EVERY_S:
            sent[0] = time.monotonic()
            conn.send(
                ("progress", {"stage": event.stage, "done": event.done, "total": event.total, "message": event.message})
            )

    work = Path(folder) / f".{plan_id}.partial"
    try:
        plan = make_bb_plan(request, progress)
        work.mkdir(exist_ok=True)
        write_bb_plan(plan, work / "plan.json")
        done = plan_path(Path(folder), plan_id)
        os.replace(work / "plan.png", done.with_suffix(".png"))
        os.replace(work / "plan.json", done)  # last: its presence says the plan is done
        reason = None
    except BBPlanError as exc:
        reason = str(exc)
    except OSError as exc:
        reason = f"cannot write the plan: {exc.strerror or exc} ({exc.filename or folder})"
    except Exception as exc:  # noqa: BLE001 - a bug must end the plan with its reason, not leave it planning
        traceback.print_exc()
        reason = f"planning failed: {failure_sentence(exc)}"
    shutil.rmtree(work, ignore_errors=True)
    conn.send(("end", reason))
    conn.close()


class PlanQueue:
    """Plans waiting and the one being made; their states on disk."""

    def __init__(self, folder: Path, *, max_waiting: int = MAX_PLANS_WAITING) -> None:
        self.folder = folder
        self.max_waiting = max_waiting
        self._ctx = mp.get_context("spawn")
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)  # a plan was queued, or the queue closes
        self._ended = threading.Condition(self._lock)  # the plan being made has ended
        self._waiting: deque[tuple[str, BBPlanRequest]] = deque()
        self._running: tuple[str, Any] | None = None  # (id, process)
        self._cancelled: dict[str, str] = {}  # id being made -> who cancelled it
        self._closed = False
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ state files
    def _state_path(self, plan_id: str) -> Path:
        return self.folder / f"{plan_id}{_STATE_SUFFIX}"

    def _write_state(self, plan_id: str, state: dict[str, Any]) -> None:
        write_json_atomically(self._state_path(plan_id), state, indent=None)

    def _end(self, plan_id: str, state: str, reason: str) -> None:
        current = self.state(plan_id) or {"id": plan_id}
        try:
            self._write_state(plan_id, {**current, "state": state, "reason": reason, "ended": utc_now()})
        except OSError as exc:  # a full disk: the plan is already over; say so in the log
            log.error("plan %s %s (%s), and its state could not be written: %s", plan_id, state, reason, exc)

    def _progress(self, plan_id: str, progress: dict[str, Any]) -> None:
        current = self.state(plan_id)
        if current is not None and current.get("state") == PLANNING:
            change = (
                {"expected_s": progress["expected_s"]} if progress["stage"] == "duration" else {"progress": progress}
            )
            with contextlib.suppress(OSError):  # a full disk: the plan goes on, its record shows older progress
                self._write_state(plan_id, {**current, **change})

    def state(self, plan_id: str) -> dict[str, Any] | None:
        """A plan's state record while it waits or is made, or once it failed or was cancelled; None otherwise."""
        try:
            return json.loads(self._state_path(plan_id).read_text())
        except (OSError, ValueError):
            return None

    def states(self) -> list[tuple[float, dict[str, Any]]]:
        """Every state record (plans not done), each with the time it last changed (``st_mtime``)."""
        found = []
        for path in self.folder.glob(f"*{_STATE_SUFFIX}"):
            with contextlib.suppress(OSError, ValueError):
                found.append((path.stat().st_mtime, json.loads(path.read_text())))
        return found

    # ------------------------------------------------------------------ requests
    def submit(self, request: BBPlanRequest, owner: str, asked: dict[str, Any]) -> dict[str, Any]:
        """Queue a plan; its state record (``asked``: what the list shows while it is made). :class:`PlansBusy` when
        the queue is full."""
        with self._lock:
            if self._closed:
                raise PlansBusy("the service is stopping")
            being_made = self._running is not None and not plan_path(self.folder, self._running[0]).exists()
            if len(self._waiting) + being_made >= self.max_waiting:
                raise PlansBusy(f"{self.max_waiting} plans are already waiting or being made (one at a time)")
            plan_id = uuid.uuid4().hex[:12]
            state = {"id": plan_id, "state": PLANNING, "owner": owner, "created": utc_now(), **asked}
            self.folder.mkdir(parents=True, exist_ok=True)  # the data directory may have been tidied by hand
            self._write_state(plan_id, state)
            self._waiting.append((plan_id, request))
            self._wake.notify()
        return state

    def cancel(self, plan_id: str, who: str) -> None:
        """Stop a plan waiting or being made (:class:`PlanEnded` when it has already ended)."""
        with self._lock:
            for item in self._waiting:
                if item[0] == plan_id:
                    self._waiting.remove(item)
                    self._end(plan_id, CANCELLED, f"cancelled by {who}")
                    return
            if self._running is not None and self._running[0] == plan_id:
                self._cancelled[plan_id] = who
                self._running[1].kill()
                self._ended.wait_for(lambda: self._running is None or self._running[0] != plan_id, timeout=10.0)
                return
        raise PlanEnded(f"plan {plan_id} has already ended")

    # ------------------------------------------------------------------ life
    def start(self) -> None:
        """Plans left planning by a previous process failed; start making plans."""
        self.folder.mkdir(parents=True, exist_ok=True)
        for leftover in self.folder.glob(".*.partial"):
            shutil.rmtree(leftover, ignore_errors=True)
        for _, state in self.states():
            if state.get("state") == PLANNING:
                self._end(state["id"], FAILED, STOPPED_REASON)
        self._thread = threading.Thread(target=self._loop, name="bb-plans", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """End the plan being made and every waiting one (failed: the service stopped)."""
        with self._lock:
            self._closed = True
            for plan_id, _ in self._waiting:
                self._end(plan_id, FAILED, STOPPED_REASON)
            self._waiting.clear()
            if self._running is not None:
                self._running[1].kill()
            self._wake.notify()
        if self._thread is not None:
            self._thread.join(10.0)

    def _loop(self) -> None:
        while True:
            with self._lock:
                while not self._waiting and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                plan_id, request = self._waiting.popleft()
                receive, send = self._ctx.Pipe(duplex=False)
                process = self._ctx.Process(
                    target=_make_plan,
                    name=f"orbitct-plan-{plan_id}",
                    daemon=True,
                    args=(request, str(self.folder), plan_id, os.getpid(), send),
                )
                try:
                    process.start()
                except OSError as exc:  # no process to be had (limits, memory): this plan fails, the queue goes on
                    receive.close()
                    send.close()
                    self._end(plan_id, FAILED, f"cannot start the planning process: {exc}")
                    continue
                send.close()
                self._running = (plan_id, process)
            reason: str | None = "the planning process ended without an answer"
            with contextlib.suppress(EOFError, OSError):
                while True:
                    kind, payload = receive.recv()
                    if kind == "end":
                        reason = payload
                        break
                    self._progress(plan_id, payload)
            receive.close()
            with self._lock:  # the answer ends the plan's turn; its process still has to exit (joined below)
                self._running = None
                who = self._cancelled.pop(plan_id, None)
                if plan_path(self.folder, plan_id).exists():  # done, even if a cancel came too late
                    self._state_path(plan_id).unlink(missing_ok=True)
                    log.info("plan %s done", plan_id)
                elif who is not None:
                    self._end(plan_id, CANCELLED, f"cancelled by {who}")
                elif self._closed:
                    self._end(plan_id, FAILED, STOPPED_REASON)
                else:
                    log.warning("plan %s failed: %s", plan_id, reason)
                    self._end(plan_id, FAILED, reason or "the planning process ended without writing the plan")
                self._ended.notify_all()
            process.join()


__all__ = [
    "CANCELLED",
    "DONE",
    "FAILED",
    "MAX_PLANS_WAITING",
    "PLANNING",
    "PlanEnded",
    "PlanQueue",
    "PlansBusy",
    "plan_path",
]
