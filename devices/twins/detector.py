"""Flat-panel detector twin: renders frames with the analytic simulator at the world's true object pose.

Served over TCP with the frame protocol documented in :mod:`devices.detector`. Commands:
``IDN?``, ``SHAPE?`` (rows cols pitch_col pitch_row binning), ``BIN n`` (1, 2, 4),
``TRIGMODE SOFTWARE|XRAY``, ``TRIGMODE?``, ``ARM``, ``DISARM``, ``TRIG`` (software trigger, a
projection under the world's kV/mA/exposure), ``DARK``, ``FLAT``, ``STATE?``, ``FRAME? ms``.
In XRAY mode an armed panel takes a projection for every completed generator exposure
(``SimWorld.xray_frame_counter``). :class:`LineTwinServer` is the protocol server the C-arm
twin reuses.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from devices.detector import (
    DEFAULT_PIXELS,
    ERR_BAD_ARG,
    ERR_DEVICE,
    ERR_NO_FRAME,
    ERR_NOT_ARMED,
    ERR_UNKNOWN,
    PANEL_MM,
    Frame,
    encode_frame,
)
from devices.twins.world import SimWorld, get_world
from devices.twins.xray import TwinFaults
from orbitct.geometry import Panel
from orbitct.geometry import ViewGeometry

XRAY_POLL_S = 0.002
Renderer = Callable[[str, ViewGeometry, float, float, float, np.random.Generator], NDArray[np.uint16]]


class CommandError(Exception):
    """A command the twin refuses: becomes ``ERR <code> <text>``."""

    def __init__(self, code: int, text: str) -> None:
        super().__init__(text)
        self.code, self.text = code, text


class LineTwinServer:
    """TCP server of the frame protocol: command lines in, ``OK``/``ERR`` lines and frames out, faults on request."""

    model = "orbitct twin"
    serial = "0000"
    firmware = "1.0"

    def __init__(self) -> None:
        self.faults = TwinFaults()
        self.frames: asyncio.Queue[Frame | str] | None = None  # a str reports a frame that failed
        self.frame_number = 0
        self.commands_seen: list[str] = []
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task[Any]] = set()

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen on ``host:port`` (0 = any free port); returns the port."""
        self.frames = asyncio.Queue()
        self._server = await asyncio.start_server(self._serve, host, port)
        await self.started()
        return int(self._server.sockets[0].getsockname()[1])

    async def started(self) -> None:
        """Hook for subclasses (background tasks)."""

    async def stop(self) -> None:
        """Close every connection and the listener."""
        for task in list(self._tasks):
            task.cancel()
        for w in list(self._writers):
            w.close()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None

    def spawn(self, coro: Any) -> asyncio.Task[Any]:
        """Run a background task that :meth:`stop` cancels."""
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def drop_connections(self) -> None:
        """Close every client connection now."""
        for w in list(self._writers):
            w.transport.abort()

    # ---------------------------------------------------------------- frames
    def next_number(self) -> int:
        """Number for a frame being taken now."""
        self.frame_number += 1
        return self.frame_number

    def push_frame(self, number: int, data: NDArray[np.uint16], kind: str, meta: dict[str, Any], timestamp: float | None = None) -> None:
        """Queue frame ``number`` taken at ``timestamp`` (default now), unless a missing-frame fault swallows it."""
        if self.faults.take("missing_frame", f"frame {number};"):
            return
        assert self.frames is not None
        self.frames.put_nowait(Frame(np.asarray(data, np.uint16), number, time.time() if timestamp is None else timestamp, kind, meta))

    def clear_frames(self) -> None:
        """Discard queued frames."""
        assert self.frames is not None
        while not self.frames.empty():
            self.frames.get_nowait()

    async def cmd_frame_q(self, args: list[str]) -> bytes:
        """``FRAME? ms``: the next queued frame, waiting up to ``ms``."""
        timeout_ms = _int_arg(args, 0, default=0)
        assert self.frames is not None
        try:
            frame = await asyncio.wait_for(self.frames.get(), timeout_ms / 1000.0) if timeout_ms else self.frames.get_nowait()
        except (asyncio.TimeoutError, asyncio.QueueEmpty):
            raise CommandError(ERR_NO_FRAME, f"no frame within {timeout_ms} ms") from None
        if isinstance(frame, str):
            raise CommandError(ERR_DEVICE, frame)
        return encode_frame(frame)

    async def cmd_idn_q(self, args: list[str]) -> str:
        """``IDN?``: model, serial, firmware."""
        return f"{self.model},{self.serial},{self.firmware}"

    # ---------------------------------------------------------------- serving
    def _handler(self, verb: str) -> Callable[[list[str]], Any] | None:
        name = "cmd_" + verb.lower().replace("?", "_q")
        fn = getattr(self, name, None)
        return fn if callable(fn) and name.startswith("cmd_") else None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        try:
            while True:
                raw = await reader.readline()
                if not raw:
                    break
                line = raw.decode("latin-1").strip()
                if not line:
                    continue
                self.commands_seen.append(line)
                if self.faults.latency_s > 0:
                    await asyncio.sleep(self.faults.latency_s)
                if self.faults.take("drop", line):
                    writer.transport.abort()
                    break
                reply = await self._dispatch(line)
                if self.faults.take("garble", line):
                    reply = garble_line(reply)
                writer.write(reply)
                await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            self._writers.discard(writer)
            writer.close()

    async def _dispatch(self, line: str) -> bytes:
        verb, *args = line.split()
        if self.faults.take("error", line):
            return f"ERR {ERR_DEVICE} injected device error on {verb}\n".encode()
        fn = self._handler(verb)
        if fn is None:
            return f"ERR {ERR_UNKNOWN} unknown command {verb!r}\n".encode()
        try:
            result = fn(args)
            if inspect.isawaitable(result):
                result = await result
        except CommandError as exc:
            return f"ERR {exc.code} {exc.text}\n".encode()
        if isinstance(result, bytes):
            return result
        return (f"OK {result}" if result else "OK").encode() + b"\n"


def garble_line(reply: bytes) -> bytes:
    """Corrupt the first line of a reply but keep its LF, so the client reads garbage, not silence."""
    head, sep, rest = reply.partition(b"\n")
    bad = bytes(b ^ 0x5A for b in head).replace(b"\n", b"?")
    return bad + sep + rest


def _int_arg(args: list[str], i: int, *, default: int | None = None) -> int:
    try:
        return int(args[i])
    except IndexError:
        if default is not None:
            return default
        raise CommandError(ERR_BAD_ARG, "missing integer argument") from None
    except ValueError:
        raise CommandError(ERR_BAD_ARG, f"not an integer: {args[i]!r}") from None


REFERENCE_KV, REFERENCE_MAS = 90.0, 0.01  # settings at which the panel's open field reads DetectorModel.flat_counts


def simulator_renderer(phantom: Any, model: Any = None) -> Renderer:
    """Counts from :mod:`orbitct.simulator`: exact line integrals of ``phantom`` and its detector model.

    The open-field signal scales with ``(kV / 90)^2 * mA * s / 0.01 mAs`` (capped below saturation);
    attenuation is monochromatic (the phantom's mu), so kV changes brightness, not contrast.
    """
    from orbitct.simulator import DetectorModel, line_integrals

    base = model if model is not None else DetectorModel()
    models: dict[float, Any] = {}

    def scaled(kv: float, ma: float, exposure_ms: float) -> Any:
        dose = (kv / REFERENCE_KV) ** 2 * (ma * exposure_ms / 1000.0) / REFERENCE_MAS
        counts = float(np.clip(base.flat_counts * dose, 1.0, 0.9 * (base.saturation_adu - base.dark_offset_adu)))
        key = round(counts, 3)
        if key not in models:
            models[key] = type(base)(**{**base.model_dump(), "flat_counts": counts})  # fresh cached maps
        return models[key]

    def render(kind: str, view: ViewGeometry, kv: float, ma: float, exposure_ms: float, rng: np.random.Generator) -> NDArray[np.uint16]:
        shape = view.panel.shape
        if kind == "dark":
            return base.dark(rng, shape)
        m = scaled(kv, ma, exposure_ms)
        if kind == "flat":
            return m.flat(rng, shape)
        return m.expose(line_integrals(phantom, view, 0), rng)

    return render


class DetectorTwin(LineTwinServer):
    """Simulated flat panel on a fixed source/detector (reference view), imaging the world's object."""

    model = "orbitct SimPanel"
    serial = "DP-0001"
    firmware = "1.0"

    def __init__(
        self,
        world: SimWorld | None = None,
        *,
        rows: int = DEFAULT_PIXELS,
        cols: int | None = None,
        panel_mm: float = PANEL_MM,
        pitch_mm: Any = None,
        sad_mm: float = 785.0,
        sdd_mm: float = 1200.0,
        phantom: Any = "A",
        seed: int = 0,
        detector_model: Any = None,
    ) -> None:
        super().__init__()
        self.world = world if world is not None else get_world("bench")
        cols = rows if cols is None else cols
        rows, cols = int(rows), int(cols)
        if pitch_mm is None:
            pitch = (float(panel_mm) / cols, float(panel_mm) / rows)
        else:  # one pitch, "col,row" text or a pair
            parts = [float(v) for v in (pitch_mm.split(",") if isinstance(pitch_mm, str) else np.atleast_1d(pitch_mm))]
            pitch = (parts[0], parts[-1])
        self.panel = Panel(rows, cols, *pitch)
        self.sad_mm, self.sdd_mm = float(sad_mm), float(sdd_mm)
        self.binning = 1
        self.mode = "SOFTWARE"
        self.armed = False
        self.rng = np.random.default_rng(int(seed))
        self.detector_model = detector_model
        self._renderer: Renderer | None = None
        self._renderer_lock = threading.Lock()
        self._phantom_spec = phantom
        self._seen_exposures = 0
        self._rendering: asyncio.Task[Any] | None = None
        self.rendering = 0  # frames taken whose pixels are still being rendered

    # ------------------------------------------------------------- rendering
    def set_phantom(self, phantom: Any) -> None:
        """Image ``phantom`` (an ``orbitct.phantoms`` object or name) from the next frame on."""
        self._phantom_spec = phantom
        self._renderer = None

    def renderer(self) -> Renderer:
        """The frame renderer (built from the phantom on first use; thread-safe)."""
        with self._renderer_lock:
            return self._build_renderer()

    def _build_renderer(self) -> Renderer:
        if self._renderer is None:
            phantom = self._phantom_spec
            if isinstance(phantom, str):
                from orbitct.phantoms import experiment_phantom

                phantom = experiment_phantom(phantom)
            self._renderer = simulator_renderer(phantom, self.detector_model)
        return self._renderer

    @property
    def geometry(self) -> Panel:
        """Pixel grid after binning."""
        return self.panel.binned(self.binning)

    def true_view(self) -> ViewGeometry:
        """The true view now: fixed lab source/detector seen from the world's true object pose."""
        lab = ViewGeometry.from_carm(0.0, 0.0, self.sad_mm, self.sdd_mm, self.geometry)
        R, t = self.world.object_pose()
        return ViewGeometry.from_object_poses(lab, R, t)

    def start_frame(self, kind: str, kv: float, ma: float, exposure_ms: float) -> int:
        """Take a frame of ``kind`` now (pose and settings fixed now, pixels rendered in the background); its number."""
        number = self.next_number()
        meta: dict[str, Any] = {"kv": kv, "ma": ma, "exposure_ms": exposure_ms, "binning": self.binning}
        if kind == "projection":
            view = self.true_view()
            meta["truth_vectors"] = [float(x) for x in view.vectors[0]]
            meta.update(self.frame_meta())
        else:
            view = ViewGeometry.from_carm(0.0, 0.0, self.sad_mm, self.sdd_mm, self.geometry)
        rng = np.random.default_rng(int(self.rng.integers(1 << 62)))
        args = (kind, view, kv, ma, exposure_ms, rng)
        self.rendering += 1
        self._rendering = self.spawn(self._render(number, args, meta, time.time(), self._rendering))
        return number

    async def _render(
        self, number: int, args: tuple[Any, ...], meta: dict[str, Any], taken: float, previous: asyncio.Task[Any] | None
    ) -> None:
        try:  # building the renderer (phantom, compiled kernels) may take a while: not in the serving loop
            data = await asyncio.get_running_loop().run_in_executor(None, lambda: self.renderer()(*args))
        except Exception as exc:  # reported to the client at FRAME?, not lost in a background task
            data, failure = None, f"frame {number} could not be rendered: {exc}"
        if previous is not None:
            await asyncio.wait([previous])  # frames leave in the order they were taken
        self.rendering -= 1
        if data is None:
            assert self.frames is not None
            self.frames.put_nowait(failure)  # type: ignore[arg-type]
            return
        self.push_frame(number, data, args[0], meta, taken)

    def frame_meta(self) -> dict[str, Any]:
        """Extra metadata of a projection (subclasses add their pose)."""
        return {}

    def _settings(self) -> tuple[float, float, float]:
        with self.world.lock:
            return float(self.world.xray_kv), float(self.world.xray_ma), float(self.world.exposure_ms)

    async def started(self) -> None:
        """Build the renderer and compile its kernels before serving (the first frame is then as fast as any)."""
        await asyncio.get_running_loop().run_in_executor(None, self.warm_up)
        self.spawn(self._watch_generator())

    def warm_up(self) -> None:
        """Render one tiny frame of every kind: loads the phantom and compiles (or loads cached) numba kernels."""
        g = self.panel
        tiny = Panel(8, 8, g.pitch_col * g.cols / 8, g.pitch_row * g.rows / 8)
        view = ViewGeometry.from_carm(0.0, 0.0, self.sad_mm, self.sdd_mm, tiny)
        rng = np.random.default_rng(0)
        for kind in ("projection", "flat", "dark"):
            self.renderer()(kind, view, 90.0, 1.0, 10.0, rng)

    async def _watch_generator(self) -> None:
        while True:
            await asyncio.sleep(XRAY_POLL_S)
            with self.world.lock:
                count = self.world.xray_frame_counter
            new = count - self._seen_exposures
            self._seen_exposures = count
            if new > 0 and self.armed and self.mode == "XRAY":
                for _ in range(new):
                    self.start_frame("projection", *self._settings())

    # -------------------------------------------------------------- commands
    def cmd_shape_q(self, args: list[str]) -> str:
        """``SHAPE?``: rows cols pitch_col pitch_row binning."""
        g = self.geometry
        return f"{g.rows} {g.cols} {g.pitch_col:.9g} {g.pitch_row:.9g} {self.binning}"

    def cmd_bin(self, args: list[str]) -> str:
        """``BIN n``: bin n x n pixels (1, 2, 4)."""
        factor = _int_arg(args, 0)
        if factor not in (1, 2, 4) or self.panel.rows // factor < 1:
            raise CommandError(ERR_BAD_ARG, f"binning must be 1, 2 or 4, got {factor}")
        self.binning = factor
        return ""

    def cmd_trigmode(self, args: list[str]) -> str:
        """``TRIGMODE SOFTWARE|XRAY``."""
        mode = args[0].upper() if args else ""
        if mode not in ("SOFTWARE", "XRAY"):
            raise CommandError(ERR_BAD_ARG, f"trigger mode must be SOFTWARE or XRAY, got {mode!r}")
        self.mode = mode
        return ""

    def cmd_trigmode_q(self, args: list[str]) -> str:
        """``TRIGMODE?``."""
        return self.mode

    def cmd_arm(self, args: list[str]) -> str:
        """``ARM``: discard queued frames, accept triggers."""
        self.clear_frames()
        with self.world.lock:
            self._seen_exposures = self.world.xray_frame_counter
        self.armed = True
        return ""

    def cmd_disarm(self, args: list[str]) -> str:
        """``DISARM``: ignore triggers."""
        self.armed = False
        return ""

    def cmd_state_q(self, args: list[str]) -> str:
        """``STATE?``: armed, mode, frames taken, queued, rendering, binning."""
        assert self.frames is not None
        return (
            f"armed={int(self.armed)} mode={self.mode} frames={self.frame_number} queued={self.frames.qsize()} "
            f"rendering={self.rendering} binning={self.binning}"
        )

    def cmd_trig(self, args: list[str]) -> str:
        """``TRIG``: software trigger; answers the frame number."""
        if not self.armed or self.mode != "SOFTWARE":
            raise CommandError(ERR_NOT_ARMED, f"software trigger needs an armed panel in SOFTWARE mode (armed={int(self.armed)}, mode={self.mode})")
        return str(self.start_frame("projection", *self._settings()))

    def cmd_dark(self, args: list[str]) -> str:
        """``DARK``: take a dark frame; answers its number."""
        return str(self.start_frame("dark", 0.0, 0.0, self._settings()[2]))

    def cmd_flat(self, args: list[str]) -> str:
        """``FLAT``: take an open-beam frame; answers its number."""
        return str(self.start_frame("flat", *self._settings()))
