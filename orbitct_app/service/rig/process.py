"""The bench process: devices (twins with sim), the scan runner and the emergency stop, away from the web server.

The web server talks to it over three pipes: commands (request id, name, arguments), a stop pipe
read by its own thread (the fallback stop when the guard is down: it never queues behind a
command), and events back (replies, scan progress, scan end). Errors cross as ``(kind, message)``;
kinds map to HTTP statuses. A thread watches the emergency-stop latch: once a stop latches, the
running scan is aborted and scans, moves and referencing are refused until an operator resets it.
If the web server dies, the command pipe closes and this process aborts the scan and exits.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import queue
import signal
import threading
import time
import uuid
from collections.abc import Callable, Coroutine
from dataclasses import asdict
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from orbitct.progress import ProgressEvent
from orbitct_app.service.core.failures import failure_sentence
from orbitct_app.service.rig import SERVICE_STOPPED
from orbitct_app.service.rig.preview import LatestFrame

log = logging.getLogger("orbitct.service.rig.process")


class CommandError(Exception):
    """A command refused with a kind (``invalid``, ``conflict``, ``stop_latched``, ``not_found``, ``unavailable``)
    and a message."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def _plain(value: Any) -> Any:
    """JSON-ready copy of a device reading."""
    import math

    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if hasattr(value, "item"):
        return _plain(value.item())
    return str(value)


def _live_outcome(live: Any) -> dict[str, Any]:
    """What a scan's live calibration came to, for the scan's summary."""
    lc, res = live.live, live.result
    out: dict[str, Any] = {"warnings": len(live.warnings)}
    if res is None:
        out["outcome"] = (
            f"failed: {live.error}" if live.error is not None else "not finished (the scan did not complete)"
        )
        return out
    out.update(
        outcome="passed" if res.quality.passed else "QUALITY CHECK FAILED: " + "; ".join(res.quality.reasons),
        bbs=int(res.n_bbs),
        quality=res.quality.line(),
        geometry_after_last_frame_s=round(float(lc.last_frame_to_geometry_s or 0.0), 3),
    )
    return out


def classify(exc: BaseException) -> tuple[str, str]:
    """``(kind, message)`` of an error raised by a command."""
    from acquire.errors import AcquireError, DiskSpaceError, NotReadyError, ScanStateError
    from devices.errors import (
        DeviceError,
        DeviceTimeoutError,
        FaultActiveError,
        InterlockOpenError,
        NotConnectedError,
        NotReferencedError,
        OutOfLimitsError,
    )

    text = str(exc) or "no message"
    if isinstance(exc, CommandError):
        return exc.kind, text
    if isinstance(exc, (ScanStateError, NotReadyError)):
        return "conflict", text
    if isinstance(exc, DiskSpaceError):
        return "insufficient_storage", text
    if isinstance(exc, AcquireError):
        return "invalid", text
    if isinstance(exc, OutOfLimitsError):
        return "invalid", text
    if isinstance(exc, (NotReferencedError, InterlockOpenError, FaultActiveError)):
        return "conflict", text
    if isinstance(exc, (DeviceTimeoutError, NotConnectedError)):
        return "unavailable", text
    if isinstance(exc, DeviceError):
        return "conflict", text
    if isinstance(exc, ValueError):
        return "invalid", text
    if isinstance(exc, (TypeError, KeyError)):
        return "invalid", f"the command has a value of the wrong kind or lacks one ({text}); check its parameters"
    return "error", failure_sentence(exc)


class RigServer:
    """Runs in the bench process: executes commands on the bench loop, reports scan progress."""

    def __init__(
        self,
        config_path: Path,
        sim: bool,
        events: Connection,
        *,
        links: dict[str, Any] | None = None,
        latch: Any = None,
    ) -> None:
        self.config_path, self.sim, self._events = Path(config_path), sim, events
        self.links = links  # where the devices are (twins of the simulated bench included); None: from the config
        self.latch = latch
        self.config: Any = None
        self.rig: Any = None
        self.runner: Any = None
        self.scan_id: str | None = None
        self.preview = LatestFrame()
        self.live: Any = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._outbox: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._sender = threading.Thread(target=self._send_out, name="bench-sender", daemon=True)
        self._sender.start()
        self._closing = asyncio.Event()
        self._tasks: set[asyncio.Task[Any]] = set()  # commands, scans and halts in flight (held until done)
        self._close_reason = f"{SERVICE_STOPPED} (shut down)"

    def send(self, *message: Any) -> None:
        """Queue one message to the web server; never blocks (a busy web server must not slow the scan down)."""
        self._outbox.put(message)

    def _send_out(self) -> None:
        """Sender thread: writes the queued messages in order (dropped once the web server is gone)."""
        while (message := self._outbox.get()) is not None:
            with contextlib.suppress(OSError, EOFError, BrokenPipeError):
                self._events.send(message)

    def close_outbox(self, timeout_s: float = 5.0) -> None:
        """Send what is queued, then end the sender thread."""
        self._outbox.put(None)
        self._sender.join(timeout_s)

    # ---------------------------------------------------------------- lifecycle
    async def serve(self, commands: Connection, stops: Connection) -> None:
        """Connect, then run commands until ``shutdown`` or the web server disappears."""
        from acquire.config import load_config
        from acquire.rigs import DeviceLink, open_rig

        self.loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # systemctl stop, a closed terminal, Ctrl-C
            self.loop.add_signal_handler(sig, self._shutdown, f"{SERVICE_STOPPED} ({signal.Signals(sig).name})")
        async with contextlib.AsyncExitStack() as stack:
            try:
                self.config = load_config(self.config_path)
                links = None if self.links is None else {k: DeviceLink(*v) for k, v in self.links.items()}
                self.rig = await stack.enter_async_context(open_rig(self.config, sim=self.sim, links=links))
                for device in self.rig.devices:  # no motion, no high voltage while a stop is latched, whoever asks
                    if hasattr(device, "interlock"):
                        device.interlock = self._latched_reason
                self.send("connected", self._describe_config())
            except Exception as exc:  # noqa: BLE001 - reported to the web server, which stays up degraded
                self.send("connect_failed", classify(exc)[1])
                return
            threading.Thread(
                target=self._read, args=(commands, self._on_command), name="bench-commands", daemon=True
            ).start()
            threading.Thread(target=self._read, args=(stops, self._on_stop), name="bench-stop", daemon=True).start()
            if self.latch is not None:
                threading.Thread(target=self._watch_latch, name="bench-latch", daemon=True).start()
            await self._closing.wait()
            if self.runner is not None and self.scan_id is not None:
                self.runner.abort(self._close_reason)
                while self.scan_id is not None:
                    await asyncio.sleep(0.05)

    def _describe_config(self) -> dict[str, Any]:
        return {"kind": type(self.config).__name__, "sim": self.sim}

    def _read(self, conn: Connection, handler: Any) -> None:
        """Reader thread: hand each message to the loop; a closed pipe means the web server is gone."""
        assert self.loop is not None
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                self.loop.call_soon_threadsafe(self._shutdown, f"{SERVICE_STOPPED} (its web process ended)")
                return
            self.loop.call_soon_threadsafe(handler, message)

    def _shutdown(self, reason: str) -> None:
        self._close_reason = reason
        self._closing.set()

    def _spawn(self, coro: Coroutine[Any, Any, Any]) -> None:
        """Run ``coro`` as a task of the loop, held until it ends (the loop keeps only weak references)."""
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ---------------------------------------------------------------- commands
    def _on_command(self, message: tuple[int, str, dict[str, Any]]) -> None:
        req_id, name, args = message
        if name == "shutdown":
            self._shutdown(str(args.get("reason", f"{SERVICE_STOPPED} (shut down)")))
            self.send("reply", req_id, True, None)
            return
        self._spawn(self._run_command(req_id, name, args))

    async def _run_command(self, req_id: int, name: str, args: dict[str, Any]) -> None:
        try:
            handler = getattr(self, f"cmd_{name}", None)
            if handler is None:
                raise CommandError("invalid", f"unknown bench command {name!r}")
            result = await handler(**args)
            self.send("reply", req_id, True, result)
        except Exception as exc:  # every failure goes back as (kind, message)
            kind, text = classify(exc)
            if kind == "error":  # nothing we expected: the details to this process's log, an incident to the caller
                incident = uuid.uuid4().hex[:12]
                log.error("internal error %s in bench command %r", incident, name, exc_info=exc)
                text = f"an internal error in the bench process stopped the command (incident {incident}): {text}"
            self.send("reply", req_id, False, (kind, text))

    def _device(self, name: str) -> Any:
        if self.rig is None:
            raise CommandError("unavailable", "no devices are connected")
        devices = {d.name: d for d in self.rig.devices}
        if name not in devices:
            raise CommandError("not_found", f"no device {name!r}; known: {', '.join(devices)}")
        return devices[name]

    def _idle(self, action: str) -> None:
        self._unlatched(action)
        if self.scan_id is not None:
            raise CommandError("conflict", f"the bench is running scan {self.scan_id}; maintenance waits until it ends")

    def _unlatched(self, action: str) -> None:
        why = self.latch.refusal(action) if self.latch is not None else None
        if why:
            raise CommandError("stop_latched", why)

    async def _state(self, dev: Any) -> dict[str, Any]:
        return {"device": _plain(asdict(await dev.describe())), "state": _plain(await dev.read())}

    async def cmd_describe(self) -> list[dict[str, Any]]:
        """Every device's description."""
        if self.rig is None:
            return []
        return [_plain(asdict(info)) for info in await self.rig.describe()]

    async def cmd_device_state(self, name: str) -> dict[str, Any]:
        """Description and reading of one device."""
        return await self._state(self._device(name))

    async def cmd_reference(self, name: str) -> dict[str, Any]:
        """Reference a motion device."""
        self._idle("referencing")
        dev = self._device(name)
        if not hasattr(dev, "reference"):
            raise CommandError("invalid", f"device {name} has no axes to reference")
        await dev.reference()
        return await self._state(dev)

    async def cmd_move(self, name: str, targets: dict[str, float]) -> dict[str, Any]:
        """Maintenance move of some axes (limits checked by the driver before anything moves)."""
        self._idle("moves")
        dev = self._device(name)
        if not hasattr(dev, "move"):
            raise CommandError("invalid", f"device {name} has no axes to move")
        known = {a.name for a in (await dev.describe()).axes}
        unknown = sorted(set(targets) - known)
        if unknown:
            raise CommandError("invalid", f"device {name} has no axes {unknown}; its axes are {sorted(known)}")
        from devices.gcs.device import ServoOffError

        try:
            await dev.move(targets)
        except ServoOffError as exc:  # the driver speaks Python; the fix over REST is the reference route
            off = ", ".join(exc.axes)
            raise CommandError(
                "conflict",
                f"{name}: servo is off on {off}; POST /devices/{name}/reference switches "
                "it on and references the axes; nothing moved",
            ) from None
        return await self._state(dev)

    async def cmd_reset_fault(self, name: str) -> dict[str, Any]:
        """Clear a generator fault whose cause is gone (refused, naming the cause, while it persists); it switches
        nothing on, so it is allowed while an emergency stop is latched."""
        if self.scan_id is not None:
            raise CommandError(
                "conflict", f"the bench is running scan {self.scan_id}; a fault reset waits until it ends"
            )
        dev = self._device(name)
        if not hasattr(dev, "reset_fault"):
            raise CommandError("invalid", f"device {name} has no fault to reset (only an X-ray generator has)")
        await dev.reset_fault()
        return await self._state(dev)

    async def cmd_stop_device(self, name: str) -> dict[str, Any]:
        """Halt one device (X-ray generator: X-rays off)."""
        dev = self._device(name)
        if hasattr(dev, "xray_off"):
            await dev.xray_off()
        elif hasattr(dev, "stop"):
            await dev.stop()
        return await self._state(dev)

    def _request(self, spec: dict[str, Any]) -> Any:
        from acquire.runner import ScanRequest

        return ScanRequest(
            config=self.config,
            out=Path(spec["out"]),
            orbit=spec["orbit"],
            orbit_params=spec["params"],
            errors=spec["errors"],
            error_params=spec.get("error_params", {}),
            seed=spec["seed"],
            mode=spec["mode"],
            sim=self.sim,
            frame_rate_hz=spec.get("frame_rate_hz"),
        )

    async def cmd_preflight(self, spec: dict[str, Any]) -> None:
        """Plan the scan and check it against every limit; nothing moves."""
        from acquire.runner import build_plan
        from acquire.storage import check_room

        req = self._request(spec)
        cfg = req.resolved_config()
        if self.rig is None:
            raise CommandError("unavailable", "no devices are connected")
        plan = build_plan(req, cfg)
        check_room(req.out, plan.panel, plan.n_frames, cfg.storage.reserve_mb)
        await self.rig.preflight(plan, req.mode, req.frame_rate_hz or cfg.exposure.frame_rate_hz)

    async def cmd_start_scan(self, scan_id: str, spec: dict[str, Any]) -> None:
        """Start a scan in the background; refused while another runs."""
        from acquire.runner import ScanRunner

        self._unlatched("scans")
        if self.scan_id is not None:
            raise CommandError("conflict", f"the bench is busy with scan {self.scan_id}; one scan at a time")
        req = self._request(spec)
        self.scan_id = scan_id
        live = self.live = self._live_calibration(scan_id, spec, req)
        self.preview = LatestFrame(
            marks=None if live is None else lambda: live.live.latest_marks if live.live else None
        )
        subscribers = [self.preview] + ([live] if live is not None else [])
        self.runner = ScanRunner(
            req,
            progress=lambda ev: self._progress(scan_id, ev),
            rig=self.rig,
            interlock=self._latched_reason,
            subscribers=subscribers,
        )
        self._spawn(self._scan(scan_id, self.runner, Path(spec["out"])))

    def _live_calibration(self, scan_id: str, spec: dict[str, Any], req: Any) -> Any:
        """The live calibration subscriber a scan asked for (``calibrate: live``), its warnings sent as scan events."""
        if spec.get("calibrate", "none") != "live":
            return None
        from calib.errors import CalibrationError
        from orbitct_app.live_calibration import LiveCalibrationSubscriber

        diameter = spec.get("bb_diameter_mm") or (req.resolved_config().sim.bb_diameter_mm if self.sim else None)
        if not diameter:
            raise CommandError("invalid", "live calibration needs bb_diameter_mm (the size of the BBs on the object)")
        try:
            return LiveCalibrationSubscriber(
                spec["out"],
                float(diameter),
                abort_on=spec.get("abort_on", ()),
                lost_frames=int(spec.get("lost_frames", 10)),
                on_warning=lambda w: self.send("scan_warning", scan_id, w.as_dict()),
                progress=self._calibration_events(scan_id),
            )
        except CalibrationError as exc:
            raise CommandError("invalid", str(exc)) from None

    async def _scan(self, scan_id: str, runner: Any, path: Path) -> None:
        from orbitct_app.service.core.files import summarize_scan

        state, reason, timing, elapsed = "failed", "", {}, None
        try:
            result = await runner.run()
            state, reason = result.status, result.reason
            timing, elapsed = {k: float(v) for k, v in dict(result.timing).items()}, float(result.elapsed_s)
        except asyncio.CancelledError:
            state, reason = "aborted", "cancelled"
        except Exception as exc:  # noqa: BLE001 - pre-flight refusals, configuration and device errors
            state, reason = "failed", classify(exc)[1]
        finally:  # the service hears how every scan ended, whatever its file looks like
            if self.live is not None:
                await asyncio.to_thread(self.live.wait)  # the final solve, in its own thread (this loop stays free)
            summary: dict[str, Any] = {}
            try:
                if path.exists():
                    summary = await asyncio.get_running_loop().run_in_executor(None, summarize_scan, path)
            except Exception as exc:  # noqa: BLE001
                summary = {"error": f"scan file unreadable: {failure_sentence(exc)}".replace(str(path), path.name)}
            if timing:
                summary["timing"], summary["elapsed_s"] = timing, elapsed
            if self.live is not None:
                summary["live_calibration"] = _live_outcome(self.live)
            self.scan_id, self.runner, self.live = None, None, None
            self.send("scan_end", scan_id, state, reason, summary)

    def _calibration_events(self, scan_id: str, every_s: float = 0.5) -> Callable[[ProgressEvent], None]:
        """The live calibration's per-frame figures (BBs, RPE, predicted error) as scan events, at most one per
        ``every_s`` (viewers see about one per second; a per-frame stream would cost the scan)."""
        last = [-1e9]

        def send(event: ProgressEvent) -> None:
            now = time.monotonic()
            if event.stage != "live-calibration" or now - last[0] < every_s:
                return
            last[0] = now
            self.send(
                "scan_calibration",
                scan_id,
                {
                    "done": int(event.done),
                    "total": int(event.total),
                    "message": event.message,
                    "metrics": {k: float(v) for k, v in dict(event.metrics).items()},
                },
            )

        return send

    def _progress(self, scan_id: str, event: ProgressEvent) -> None:
        self.send(
            "progress",
            scan_id,
            {
                "stage": event.stage,
                "done": int(event.done),
                "total": int(event.total),
                "message": event.message,
                "metrics": {k: float(v) for k, v in dict(event.metrics).items()},
            },
        )

    async def cmd_latest_frame(self, scan_id: str) -> dict[str, Any] | None:
        """The running scan's newest frame, small and 8-bit (None before its first frame)."""
        self._running(scan_id)
        return await asyncio.get_running_loop().run_in_executor(None, self.preview.snapshot)

    async def cmd_pause(self, scan_id: str) -> None:
        """Pause at the next frame boundary."""
        self._running(scan_id).pause()

    async def cmd_resume(self, scan_id: str) -> None:
        """Resume a paused scan (refused while an emergency stop is latched)."""
        runner = self._running(scan_id)
        self._unlatched("resuming a scan")
        runner.resume()

    async def cmd_abort(self, scan_id: str, reason: str) -> None:
        """Abort: halt, X-rays off, file marked aborted."""
        self._running(scan_id).abort(reason)

    def _running(self, scan_id: str) -> Any:
        if self.scan_id != scan_id or self.runner is None:
            raise CommandError("conflict", f"scan {scan_id} is not running on the bench")
        return self.runner

    # ---------------------------------------------------------------- emergency stop
    def _watch_latch(self) -> None:
        """Thread: once a stop latches (the guard, or the web server), abort the running scan."""
        assert self.loop is not None
        while not self._closing.is_set():
            if not self.latch.flag.wait(1.0, poll_s=0.01):
                continue
            reason = self._latched_reason()
            if self.scan_id is not None and reason is not None:
                self.loop.call_soon_threadsafe(self._abort_running, reason)
            time.sleep(0.02)

    def _latched_reason(self) -> str | None:
        """Why scans must stop now: the latched emergency stop (who and why), or None while it is clear."""
        if self.latch is None or not self.latch.flag.is_set():
            return None
        state = self.latch.state()
        reason = state.get("reason") or "emergency stop"
        return reason if reason.startswith("emergency stop") else f"emergency stop by {state.get('by')}: {reason}"

    def _abort_running(self, reason: str) -> None:
        if self.runner is not None:
            self.runner.abort(reason)

    def _on_stop(self, message: tuple[int, str]) -> None:
        req_id, reason = message
        scan_id = self.scan_id
        if self.runner is not None:
            self.runner.abort(reason)
        self._spawn(self._halt(req_id, scan_id))

    async def _halt(self, req_id: int, scan_id: str | None) -> None:
        """The fallback stop (no guard): halt every device over the rig's own links and read each back."""
        from devices.halt import halt_and_verify, summary

        if self.rig is None:
            self.send("reply", req_id, False, ("unavailable", "no bench devices are connected"))
            return
        checks = await halt_and_verify(self.rig.devices, timeout_s=1.0)
        halted, message = summary(checks)
        self.send(
            "reply",
            req_id,
            True,
            {"halted": halted, "message": message, "scan_aborted": scan_id, "devices": [c.to_json() for c in checks]},
        )


def rig_main(
    config_path: str,
    sim: bool,
    commands: Connection,
    stops: Connection,
    events: Connection,
    nice: int = 0,
    links: dict[str, Any] | None = None,
    data_dir: str | None = None,
    flag: Any = None,
) -> None:
    """Entry point of the bench process (asks for priority ``nice`` over the web server where allowed)."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s bench: %(message)s")
    # The web server starts this process as a daemon (it dies with the server); here it may start its own
    # processes (a live calibration's worker, which ends by itself if this process disappears).
    import multiprocessing

    multiprocessing.current_process().daemon = False
    if nice < 0:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except OSError:
            log.info("bench process priority stays normal (raising it needs root or CAP_SYS_NICE)")
    latch = None
    if data_dir is not None and flag is not None:
        from orbitct_app.service.safety.latch import StopLatch

        latch = StopLatch(Path(data_dir), flag)
    server = RigServer(Path(config_path), sim, events, links=links, latch=latch)
    try:
        asyncio.run(server.serve(commands, stops))
    finally:
        server.send("exited")
        server.close_outbox()
