"""Calibration while a scan runs: BBs detected and followed as frames arrive, warnings while the operator can
still act, and the geometry in the file as soon as the last frame is.

A :class:`LiveCalibration` is fed every frame of a scan, in order (:meth:`LiveCalibration.add_frame`, which only
queues the frame: the acquisition never waits for it). A worker process detects the BBs in each projection
with the same detector as ``orbitct calibrate``, follows them frame to frame (:class:`calib.follow.Follower`)
and raises warnings naming frames and positions. When the scan is complete, :meth:`LiveCalibration.finish`
identifies the BBs and estimates the geometry from the candidates already found
(:func:`calib.pipeline.calibrate_candidates`: the results and quality figures are those of the offline
calibration of the same file). Frames that arrive while more than ``max_pending`` wait are not held: they are
detected from the file after the scan, and a warning says so.
"""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing as mp
import os
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib.detect import N_FIELDS
from calib.errors import CalibrationError
from calib.follow import (
    Follower,
    LiveCalibrationError,
    LiveSettings,
    LiveWarning,
)
from calib.options import checked_options
from calib.pipeline import calibrate_candidates, frame_detector, two_flats
from calib.result import CalibrationResult
from orbitct.geometry import ViewGeometry
from orbitct.progress import ProgressCallback, report
from orbitct.scanfile import ImageKey, ScanFile

log = logging.getLogger(__name__)
WATCH_S = 0.5  # how often a wait on the worker looks whether its process is still there
FEED_STALL_S = 2.0  # a dark or flat the worker has not taken in this long: it is hung or far behind, and given up
SILENT_S = 30.0  # after the scan, a worker that has said nothing for this long is given up
STOP_WAIT_S = 5.0  # how long a scan that did not complete waits for the worker to stop before it is killed


def _end_when_orphaned(parent: int) -> None:
    """Thread of the worker: end the process once the acquisition's process is gone (killed, perhaps while a frame
    was half written into the queue, which would leave the worker waiting for the rest forever)."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(0)


def _worker(
    frames: Any,
    events: Any,
    nominal: ViewGeometry,
    image_key: NDArray[Any],
    diameter_mm: float,
    settings: LiveSettings,
    options: dict[str, Any],
) -> None:
    """The worker process: frames ``(index, frame)`` in, events out; ``("end", n_frames)`` ends the scan (the
    candidates go back), ``"stop"`` ends it without them."""
    try:
        with contextlib.suppress(OSError, AttributeError):
            os.nice(10)  # the acquisition goes first; this one catches up when a frame takes longer
        follower = Follower(nominal, image_key, diameter_mm, settings, options, lambda kind, x: events.put((kind, x)))
        events.put(("ready", None))
        threading.Thread(target=_end_when_orphaned, args=(os.getppid(),), name="orphan-watch", daemon=True).start()
        while True:
            item = frames.get()
            if item[0] == "end":
                follower.skip_to(item[1])
                events.put(
                    (
                        "done",
                        (
                            follower.candidates,
                            follower.floors,
                            follower.plan,
                            follower._deferred,
                            follower.detect_s,
                            follower.bbs_per_frame,
                            follower.d_px,
                            follower.linked(),
                            (follower.window.windows, follower.window.seconds, len(follower.rpe_mm)),
                        ),
                    )
                )
                return
            if isinstance(item, str) and item == "stop":
                events.put(("stopped", None))
                return
            follower.take(*item)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it from finish()
        events.put(("error", str(exc) or ("it ran out of memory" if isinstance(exc, MemoryError) else "it stopped")))


class LiveCalibration:
    """Calibrates a scan while its frames arrive (see the module's description).

    ``nominal``: the nominal geometry of every frame of the plan (darks and flats NaN), ``image_key``: the
    plan's image keys, ``path``: the scan file the recorder writes (read after the scan for the final solve
    and for any frame not detected live). Detection and following run in a worker process (the acquisition
    shares no interpreter lock with them); ``on_warning`` and ``progress`` are called in a thread of this one."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        nominal: ViewGeometry,
        image_key: NDArray[np.integer[Any]],
        diameter_mm: float,
        *,
        settings: LiveSettings | None = None,
        progress: ProgressCallback | None = None,
        on_warning: Callable[[LiveWarning], None] | None = None,
        **options: Any,
    ) -> None:
        if not diameter_mm or not diameter_mm > 0:
            raise LiveCalibrationError(f"live calibration needs the BB diameter in mm (> 0), got {diameter_mm!r}")
        checked_options("bundle", {**options, "diameter_mm": diameter_mm})  # refuse bad options here, not in the worker
        self.path = Path(path)
        self.options = dict(options)
        self.settings = settings or LiveSettings()
        self.image_key = np.asarray(image_key)
        self.diameter_mm = float(diameter_mm)
        self.progress = progress
        self.on_warning = on_warning
        self.n_projections = int((self.image_key == ImageKey.PROJECTION).sum())
        self.warnings: list[LiveWarning] = []
        self.detect_s = 0.0
        self.frames_detected_after_scan = 0
        self.bbs_per_frame: list[int] = []  # after the scan: BB-like blobs per projection (-1: not followed live)
        self.last_frame_s: float | None = None  # perf_counter when the last frame was handed over
        self.last_frame_to_geometry_s: float | None = None
        self.timing: dict[str, float] = {}  # after the scan: catching up, the final solve (s)
        self.latest_marks: tuple[int, list[list[float]]] | None = None  # (scan frame, [[u, v], ...] of its BBs) newest
        self._next_index = 0
        self._closed = False
        self._outcome: tuple[Any, ...] | None = None
        self._failure: str | None = None
        self._ended = threading.Event()
        self._ready = threading.Event()
        self._last_event_s = time.monotonic()  # when the worker last said something
        ctx = mp.get_context("spawn")
        self._frames = ctx.Queue(maxsize=self.settings.max_pending)
        # never wait at exit to flush frames into the pipe of a worker that is gone (the process would hang for good)
        self._frames.cancel_join_thread()
        self._events = ctx.Queue()
        self._process = ctx.Process(
            target=_worker,
            name="orbitct-live-calibration",
            daemon=True,
            args=(self._frames, self._events, nominal, self.image_key, self.diameter_mm, self.settings, self.options),
        )
        self._process.start()
        self._listener = threading.Thread(target=self._listen, name="orbitct-live-events", daemon=True)
        self._listener.start()

    def _worker_gone(self) -> str | None:
        """Why the worker process is gone without saying so (killed, crashed), or None while it runs."""
        if self._process.is_alive():
            return None
        code = self._process.exitcode
        how = f"was killed by signal {-code}" if code is not None and code < 0 else f"ended (exit code {code})"
        return f"its worker process {how}"

    def _give_up(self, why: str) -> None:
        """Stop waiting for the worker (the scan goes on; its frames calibrate offline) and end its process."""
        if self._failure is None and self._outcome is None:
            self._failure = why
        self._ended.set()
        with contextlib.suppress(Exception):
            self._process.kill()

    def _listen(self) -> None:
        while True:
            try:
                kind, x = self._events.get(timeout=WATCH_S)
                self._last_event_s = time.monotonic()
            except queue.Empty:
                gone = self._worker_gone()
                if gone is not None and self._events.empty():  # the events it sent before ending are all read
                    self._failure = self._failure or gone
                    self._ended.set()
                    return
                continue
            except (EOFError, OSError, ValueError) as exc:  # the queue's pipe broke with the worker
                self._failure = self._failure or self._worker_gone() or f"its events could not be read ({exc})"
                self._ended.set()
                return
            if kind == "warning":
                self.warnings.append(x)
                report(self.progress, "live-warning", x.frame, self.n_projections, x.message)
                if self.on_warning is not None:
                    self.on_warning(x)
            elif kind == "progress":
                report(self.progress, x[0], x[1], x[2], x[3], **x[4])
            elif kind == "marks":
                self.latest_marks = x
            elif kind == "ready":
                self._ready.set()
            elif kind in ("done", "stopped", "error"):
                if kind == "done":
                    self._outcome = x
                elif kind == "error":
                    self._failure = x
                self._ended.set()
                return

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        """Return once the worker follows frames (it starts in a process of its own, at low priority: on a busy
        machine that takes seconds); :class:`LiveCalibrationError` if it did not within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while not self._ready.wait(0.05):
            if self._ended.is_set() or not self._process.is_alive() or time.monotonic() > deadline:
                reason = self._failure or (
                    "its process ended" if not self._process.is_alive() else f"not within {timeout_s:g} s"
                )
                raise LiveCalibrationError(f"the live calibration did not start: {reason}")

    # ------------------------------------------------------------------ feeding
    def add_frame(self, index: int, image_key: int, frame: NDArray[Any]) -> None:
        """Hand over scan frame ``index`` (in order); returns at once. While ``max_pending`` frames wait, a
        projection is not sent (it is detected from the file after the scan); darks and flats always are."""
        if self._closed:
            raise LiveCalibrationError("frames after the scan ended")
        if index != self._next_index:
            raise LiveCalibrationError(f"frame {index} arrived, frame {self._next_index} was expected (in order)")
        self._next_index += 1
        self.last_frame_s = time.perf_counter()
        if self._ended.is_set():
            return  # the worker is gone (finish() says why): the scan goes on, its frames calibrate offline
        if int(image_key) != ImageKey.PROJECTION:  # a dark or flat is never dropped; the worker is, if it stalls
            try:
                self._frames.put((index, np.asarray(frame)), timeout=FEED_STALL_S)
            except queue.Full:
                self._give_up(f"its worker took no frame for {FEED_STALL_S:g} s (hung, or far behind)")
            return
        try:
            self._frames.put_nowait((index, np.asarray(frame)))
        except queue.Full:
            pass  # the worker sees the gap in the indices

    def _give_up_if_silent(self) -> None:
        if time.monotonic() - self._last_event_s > SILENT_S:
            self._give_up(f"its worker said nothing for {SILENT_S:g} s (hung)")

    # ------------------------------------------------------------------ the end
    def close(self) -> None:
        """Stop the worker without a result (a scan that did not complete: its frames calibrate offline)."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(queue.Full, ValueError, OSError):
            self._frames.put("stop", timeout=1.0)
        self._ended.wait(STOP_WAIT_S)
        self._process.join(1.0)
        if self._process.is_alive():  # hung: SIGKILL (a stopped process would hold a SIGTERM, and the exit with it)
            self._process.kill()
            self._process.join(5.0)

    def finish(self, progress: ProgressCallback | None = None) -> CalibrationResult:
        """After the recorder closed the complete file: detect what is left, identify, estimate, write
        ``/geometry/calibrated`` as ``orbitct calibrate`` does, and return the result."""
        if self._closed:
            raise LiveCalibrationError("this live calibration already ended")
        self._closed = True
        t_end = time.perf_counter()
        self._last_event_s = time.monotonic()
        while not self._ended.is_set():
            try:
                self._frames.put(("end", self._next_index), timeout=WATCH_S)
                break
            except queue.Full:
                self._give_up_if_silent()
        while not self._ended.wait(WATCH_S):  # set when the worker answers, fails, is found gone or is given up
            self._give_up_if_silent()
        self.timing["catch_up_s"] = time.perf_counter() - t_end  # the worker's backlog when the scan ended
        if self._failure is not None or self._outcome is None:
            raise LiveCalibrationError(f"the live calibration stopped: {self._failure}")
        candidates, floors, plan, deferred, self.detect_s, self.bbs_per_frame, d_px, linked, windows = self._outcome
        self.timing["windows"], self.timing["window_s"], self.timing["posed"] = (float(w) for w in windows)
        self.frames_detected_after_scan = len(deferred)
        opt = checked_options("bundle", {**self.options, "diameter_mm": self.diameter_mm})
        with ScanFile(self.path) as sf:
            proj = sf.projection_indices
            if proj.size != len(candidates):
                raise LiveCalibrationError(
                    f"{self.path}: {proj.size} projections in the file, {len(candidates)} seen live"
                )
            if deferred:
                t = time.perf_counter()
                dark, flat = sf.dark_flat()
                fd = frame_detector(dark, flat, d_px, opt, two_flats(sf))
                fd.noise = fd.estimate_noise(np.asarray(sf.frames[int(proj[0])]))  # as offline: the first projection
                floors_so_far = np.array(floors)
                for p in deferred:  # in order, searched as offline: each frame's windows come from those before
                    windows = plan.windows(p, candidates, floors_so_far)
                    found = plan.search(fd, np.asarray(sf.frames[int(proj[p])]), windows)
                    candidates[p], floors_so_far[p] = found.records, found.floor
                self.detect_s += time.perf_counter() - t
        cands = [np.zeros((0, N_FIELDS)) if c is None else c for c in candidates]
        t_solve = time.perf_counter()
        result = calibrate_candidates(
            self.path,
            cands,
            diameter_mm=self.diameter_mm,
            progress=progress or self.progress,
            detect_s=self.detect_s,
            linked=linked,
            **self.options,
        )
        self.timing["solve_s"] = time.perf_counter() - t_solve
        if self.last_frame_s is not None:
            self.last_frame_to_geometry_s = time.perf_counter() - self.last_frame_s
        result.warnings[:0] = [w.message for w in self.warnings]
        self._process.join(10.0)  # it ends by itself after the candidates (not waited for before the solve)
        with ScanFile(self.path, "r+") as sf:
            g = sf.h5["geometry/calibrated"]
            g.attrs["live"] = True
            g.attrs["live_warnings_json"] = json.dumps([w.as_dict() for w in self.warnings])
            g.attrs["live_frames_detected_after_scan"] = len(deferred)
        return result


class FinalSolve:
    """The final solve of a complete scan's live calibration (:meth:`LiveCalibration.finish`) in a thread of its
    own, so that the acquisition's loop and the signals it handles stay free. Its outcome is said in the file
    (``/geometry/calibrated`` there, or why it is missing); a failure is kept (:attr:`error`) and logged, never
    raised: the scan is complete whatever the solve does."""

    def __init__(self, live: LiveCalibration) -> None:
        self.live = live
        self._result: CalibrationResult | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="orbitct-live-final-solve", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self._result = self.live.finish()
        except CalibrationError as exc:
            self._error = exc
            log.error("live calibration of %s failed: %s", self.live.path, exc)
        except Exception as exc:
            self._error = exc
            log.exception("live calibration of %s failed", self.live.path)
        outcome = "done" if self._result is not None else f"missing: {self._error}"
        try:
            with ScanFile(self.live.path, "r+") as sf:
                sf.set_live_calibration(outcome)
        except Exception as exc:  # noqa: BLE001 - the scan's own record stands; the command says it too
            log.error("could not record the live calibration's outcome in %s: %s", self.live.path, exc)

    def wait(self, timeout_s: float | None = None) -> bool:
        """Whether the solve has ended (waiting up to ``timeout_s``)."""
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    @property
    def result(self) -> CalibrationResult | None:
        """The calibration (waits for the solve); None when it failed."""
        self.wait()
        return self._result

    @property
    def error(self) -> BaseException | None:
        """Why there is no calibration (waits for the solve); None when there is one."""
        self.wait()
        return self._error


class FinalSolveOutcome:
    """The outcome of a final solve, for the classes that start one (into ``_final``; None: none started)."""

    _final: FinalSolve | None = None

    def wait(self, timeout_s: float | None = None) -> bool:
        """Whether the final solve has ended (waiting up to ``timeout_s``; at once when none was started)."""
        return True if self._final is None else self._final.wait(timeout_s)

    @property
    def result(self) -> CalibrationResult | None:
        """The calibration of a complete scan (waits for its final solve); None when there is none."""
        return None if self._final is None else self._final.result

    @property
    def error(self) -> BaseException | None:
        """Why a complete scan has no live geometry (waits for its final solve); None when it has one."""
        return None if self._final is None else self._final.error


__all__ = [
    "FinalSolve",
    "FinalSolveOutcome",
    "LiveCalibration",
    "LiveCalibrationError",
    "LiveSettings",
    "LiveWarning",
]
