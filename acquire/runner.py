"""High-level scan API for the CLI and the REST service: request in, scan file out, with progress and control."""

from __future__ import annotations

import asyncio
import dataclasses
import signal
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from acquire.config import BenchConfig, CArmConfig, load_config
from acquire.engine import ScanEngine
from acquire.errors import AcquireError, ScanStateError
from acquire.options import ScanOptions, checked_scan_options
from acquire.plan import ScanPlan
from acquire.recorder import ScanRecorder, SimulationTruth
from acquire.records import Subscriber
from acquire.rig import Rig
from acquire.rigs import open_rig
from acquire.rigs.kinds import rig_kind
from acquire.storage import check_room
from orbitct.errorprofiles import ErrorProfileError, make_profile
from orbitct.orbits import Orbit, OrbitError, make_orbit
from orbitct.progress import ProgressCallback, ProgressEvent

CTRL_C_REASON = "interrupted by the user (Ctrl-C)"
# why a scan stopped when its process got a signal; a command line exits with 128 + the signal number
SIGNAL_REASONS: dict[int, str] = {
    signal.SIGINT: CTRL_C_REASON,
    signal.SIGTERM: "terminated by SIGTERM (kill, systemctl stop, timeout)",
    signal.SIGHUP: "hung up by SIGHUP (the terminal closed)",
}


@dataclass
class ScanRequest:
    """Everything one scan needs: configuration, output file, orbit and its parameters, errors, mode."""

    config: str | Path | BenchConfig | CArmConfig
    out: str | Path
    orbit: str = "sawtooth"
    frames: int | None = None
    orbit_params: Mapping[str, Any] = field(default_factory=dict)
    errors: str = "none"  # injected motion errors: only when asked for
    error_params: Mapping[str, Any] = field(default_factory=dict)
    seed: int = 0
    mode: str = "step"
    sim: bool = False
    detector_size: int | None = None
    frame_rate_hz: float | None = None
    overwrite: bool = False

    def options(self) -> ScanOptions:
        """The scan's options, checked (:class:`AcquireError` naming each one that is wrong)."""
        return checked_scan_options(
            orbit=self.orbit,
            orbit_params=dict(self.orbit_params),
            frames=self.frames,
            errors=self.errors,
            error_params=dict(self.error_params),
            seed=self.seed,
            mode=self.mode,
            frame_rate_hz=self.frame_rate_hz,
        )

    def resolved_config(self) -> BenchConfig | CArmConfig:
        """The configuration object (loaded and validated if a path was given)."""
        cfg = self.config if isinstance(self.config, (BenchConfig, CArmConfig)) else load_config(self.config)
        return cfg.with_detector_size(self.detector_size)


@dataclass(frozen=True)
class ScanResult:
    """How a scan ended and where its file is."""

    path: Path
    status: str
    reason: str
    n_frames: int
    n_planned: int
    elapsed_s: float
    timing: Mapping[str, float] = field(default_factory=dict)


def make_orbit_and_errors(req: ScanRequest) -> tuple[Orbit, np.ndarray, dict[str, Any]]:
    """The orbit and the injected errors (N, 6: pitch, roll, yaw, x, y, z) of a request, with the profile's description."""
    params = dict(req.orbit_params)
    if req.frames is not None:
        params["n_frames"] = int(req.frames)
    try:
        orbit = make_orbit(req.orbit, **params)
        profile = make_profile(req.errors, seed=req.seed, **dict(req.error_params))
    except (OrbitError, ErrorProfileError) as exc:
        raise AcquireError(str(exc)) from None
    return orbit, profile.sample(orbit).as_array(), profile.to_json()


def build_plan(req: ScanRequest, cfg: BenchConfig | CArmConfig) -> ScanPlan:
    """The plan of a request on the rig ``cfg`` describes (a C-arm injects no errors: its own are what is measured)."""
    req.options()
    kind = rig_kind(cfg)
    if req.mode not in kind.modes:
        modes = " or ".join(repr(m) for m in kind.modes)
        raise AcquireError(f"the {kind.name} runs scans in mode {modes}, not {req.mode!r}; choose one of those")
    if not kind.injects_errors:
        req = dataclasses.replace(req, errors="none", error_params={})
    orbit, errors, profile = make_orbit_and_errors(req)
    return kind.plan(cfg, orbit, errors, profile)


def simulation_truth(cfg: BenchConfig | CArmConfig) -> SimulationTruth:
    """Marker centres and phantom that the twins of ``cfg`` image."""
    from orbitct.phantoms.experiments import experiment_phantom

    imaged = cfg.sim.imaged()
    phantom = experiment_phantom(imaged, seed=cfg.sim.seed) if isinstance(imaged, str) else imaged
    return SimulationTruth(np.asarray(phantom.markers_xyz, dtype=float), phantom.to_json())


def start_extra(cfg: BenchConfig | CArmConfig, plan: ScanPlan, frame_rate_hz: float) -> dict[str, Any]:
    """What a scan records about its rig in ``/acquisition`` besides mode and errors."""
    return rig_kind(cfg).recorded(cfg, plan, frame_rate_hz)


class ScanRunner:
    """Runs one scan in the caller's loop (:meth:`run`) or in a background thread (:meth:`start`)."""

    def __init__(
        self,
        request: ScanRequest,
        *,
        progress: ProgressCallback | None = None,
        rig: Rig | None = None,
        interlock: Callable[[], str | None] | None = None,
        subscribers: Sequence[Subscriber] = (),
    ) -> None:
        """``subscribers`` receive the scan's events after the recorder (live analysis: it sees each frame once it
        is written, and the complete file once closed)."""
        request.options()  # refused before anything connects
        self.request = request
        self._user_progress = progress
        self._rig = rig
        self._interlock = interlock
        self._subscribers = list(subscribers)
        self.error: BaseException | None = None
        self.result: ScanResult | None = None
        self._engine: ScanEngine | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._done = threading.Event()
        self._pending_abort: str | None = None
        self._pending_pause = False
        self._state = "idle"

    # --------------------------------------------------------------- state
    @property
    def state(self) -> str:
        """``idle``, ``preflight``, ``running``, ``paused``, ``complete``, ``aborted`` or ``failed``."""
        if self._engine is not None and self._state not in ("complete", "aborted", "failed"):
            return self._engine.state
        return self._state

    def _progress(self, event: ProgressEvent) -> None:
        if self._user_progress is not None:
            self._user_progress(event)

    # ----------------------------------------------------------------- run
    async def run(self) -> ScanResult:
        """Connect (unless a rig was given), plan, pre-flight, scan, record; returns the result."""
        self._loop = asyncio.get_running_loop()
        req = self.request
        try:
            cfg = req.resolved_config()
            plan = build_plan(req, cfg)
            out = Path(req.out)
            if out.exists() and not req.overwrite:
                raise AcquireError(f"{out}: already exists (orbitct scan --overwrite replaces it)")
            check_room(out, plan.panel, plan.n_frames, cfg.storage.reserve_mb)
            rig_kind(cfg).write_program(cfg, plan, out)
            recorder = ScanRecorder(
                out,
                overwrite=req.overwrite,
                marker_diameter_mm=cfg.sim.bb_diameter_mm if req.sim else None,
                truth=simulation_truth(cfg) if req.sim else None,
                reserve_mb=cfg.storage.reserve_mb,
            )
            if self._rig is not None:
                self.result = await self._run_engine(self._rig, plan, cfg, recorder)
            else:
                async with open_rig(cfg, sim=req.sim) as rig:
                    self.result = await self._run_engine(rig, plan, cfg, recorder)
            self._state = self.result.status
            return self.result
        except BaseException as exc:
            self.error = exc
            self._state = "failed" if not isinstance(exc, (KeyboardInterrupt, asyncio.CancelledError)) else "aborted"
            raise
        finally:
            self._done.set()

    async def _run_engine(
        self, rig: Rig, plan: ScanPlan, cfg: BenchConfig | CArmConfig, recorder: ScanRecorder
    ) -> ScanResult:
        rate = float(self.request.frame_rate_hz or cfg.exposure.frame_rate_hz)
        engine = ScanEngine(
            rig,
            plan,
            motion=cfg.motion,
            frame_rate_hz=rate,
            mode=self.request.mode,
            subscribers=[recorder, *self._subscribers],
            progress=self._progress,
            start_extra=start_extra(cfg, plan, rate),
            interlock=self._interlock,
        )
        self._attach(engine)
        outcome = await engine.run()
        return ScanResult(
            Path(self.request.out),
            outcome.status,
            outcome.reason,
            outcome.n_frames,
            outcome.n_planned,
            outcome.elapsed_s,
            engine.timing,
        )

    def _attach(self, engine: ScanEngine) -> None:
        """Route pause/resume/abort to ``engine`` (and apply any that came before it existed)."""
        self._engine = engine
        if self._pending_pause:
            engine.pause()
        if self._pending_abort is not None:
            engine.abort(self._pending_abort)

    # ------------------------------------------------------- background use
    def start(self) -> None:
        """Run in a new thread with its own event loop; returns at once."""
        if self._thread is not None:
            raise ScanStateError("this runner was already started")

        def _main() -> None:
            try:
                asyncio.run(self.run())
            except BaseException:  # noqa: BLE001 - kept in self.error for wait()
                pass

        self._thread = threading.Thread(target=_main, name="orbitct-scan", daemon=True)
        self._thread.start()

    def wait(self, timeout: float | None = None) -> ScanResult:
        """Block until the scan ends; re-raises what prevented it."""
        if not self._done.wait(timeout):
            raise TimeoutError(f"scan still {self.state} after {timeout} s")
        if self.error is not None:
            raise self.error
        assert self.result is not None
        return self.result

    def _call(self, fn_name: str, *args: Any) -> None:
        engine, loop = self._engine, self._loop
        if engine is None or loop is None or loop.is_closed():
            return
        try:
            same_loop = asyncio.get_running_loop() is loop
        except RuntimeError:
            same_loop = False
        if same_loop or not loop.is_running():
            getattr(engine, fn_name)(*args)
        else:
            loop.call_soon_threadsafe(getattr(engine, fn_name), *args)

    def pause(self) -> None:
        """Pause at the next frame boundary (thread-safe)."""
        if self.state in ("complete", "aborted", "failed"):
            raise ScanStateError(f"cannot pause a scan that is {self.state}")
        self._pending_pause = True
        self._call("pause")

    def resume(self) -> None:
        """Resume a paused scan (thread-safe)."""
        if self._pending_abort is not None:
            raise ScanStateError(f"cannot resume a scan that is being aborted ({self._pending_abort})")
        if not self._pending_pause:
            raise ScanStateError(f"cannot resume a scan that is {self.state} (not paused)")
        self._pending_pause = False
        self._call("resume")

    def abort(self, reason: str = "aborted by the operator") -> None:
        """Abort now: halt axes, X-rays off, file marked aborted with ``reason`` (thread-safe)."""
        self._pending_abort = reason
        self._call("abort", reason)


def run_scan(
    request: ScanRequest, *, progress: ProgressCallback | None = None, subscribers: Sequence[Subscriber] = ()
) -> ScanResult:
    """Run one scan to its end in a fresh event loop (blocking).

    In the main thread the first SIGINT (Ctrl-C), SIGTERM (``kill``, ``systemctl stop``, ``timeout``)
    or SIGHUP (the terminal closed) aborts the scan cleanly: axes halted, X-rays off, file marked
    aborted with :data:`SIGNAL_REASONS` of that signal. A second signal acts at once (Ctrl-C raises
    KeyboardInterrupt, which still halts everything on its way out).
    """
    runner = ScanRunner(request, progress=progress, subscribers=subscribers)

    async def main() -> ScanResult:
        loop = asyncio.get_running_loop()
        installed: list[int] = []

        def first_signal(signum: int) -> None:
            runner.abort(SIGNAL_REASONS[signum])
            for sig in installed:  # the next signal takes its default action
                loop.remove_signal_handler(sig)
            installed.clear()

        if threading.current_thread() is threading.main_thread():
            for sig in SIGNAL_REASONS:
                try:
                    loop.add_signal_handler(sig, first_signal, sig)
                    installed.append(sig)
                except (NotImplementedError, RuntimeError, ValueError):
                    pass
        try:
            return await runner.run()
        finally:
            for sig in installed:
                loop.remove_signal_handler(sig)

    return asyncio.run(main())
