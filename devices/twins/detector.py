"""Flat-panel detector twin: renders frames with the analytic simulator at the world's true object pose.

Served over TCP with the frame protocol of :mod:`devices.frame_protocol`. Commands:
``IDN?``, ``SHAPE?`` (rows cols pitch_col pitch_row binning), ``BIN n`` (1, 2, 4),
``TRIGMODE SOFTWARE|XRAY``, ``TRIGMODE?``, ``ARM``, ``DISARM``, ``TRIG`` (software trigger, a
projection under the world's kV/mA/exposure), ``DARK``, ``FLAT``, ``STATE?``, ``FRAME? ms``.
In XRAY mode an armed panel takes a projection for every completed generator exposure
(``SimWorld.xray_frame_counter``).
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from devices.frame_protocol import ERR_BAD_ARG, ERR_NOT_ARMED
from devices.twins.feed import follow_bench
from devices.twins.line_server import CommandError, LineTwinServer, int_arg
from devices.twins.world import SimWorld, get_world
from orbitct.geometry import Panel, ViewGeometry
from orbitct.reference_bench import PANEL_PX, SAD_MM, SDD_MM, reference_panel

XRAY_POLL_S = 0.002
Renderer = Callable[[str, ViewGeometry, float, float, float, np.random.Generator], NDArray[np.uint16]]


REFERENCE_KV, REFERENCE_MAS = 90.0, 0.01  # settings at which the panel's open field reads DetectorModel.flat_counts


def simulator_renderer(phantom: Any, model: Any = None, beam: Any = None) -> Renderer:
    """Counts from :mod:`orbitct.simulator`: exact line integrals of ``phantom`` and its detector model.

    The open-field signal scales with ``(kV / 90)^2 * mA * s / 0.01 mAs`` (capped below saturation). With no
    ``beam`` the attenuation is monochromatic (the phantom's mu), so kV changes brightness, not contrast; with a
    polychromatic :class:`~orbitct.simulator.Beam` the spectrum follows the generator's kV, so it changes both.
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

    def render(
        kind: str, view: ViewGeometry, kv: float, ma: float, exposure_ms: float, rng: np.random.Generator
    ) -> NDArray[np.uint16]:
        shape = view.panel.shape
        if kind == "dark":
            return base.dark(rng, shape)
        m = scaled(kv, ma, exposure_ms)
        if kind == "flat":
            return m.flat(rng, shape, view.panel.mean_pitch_mm)
        spectrum = None if beam is None else beam.at_kv(kv)
        return m.expose(line_integrals(phantom, view, 0, beam=spectrum), rng, view.panel.mean_pitch_mm)

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
        rows: int = PANEL_PX,
        cols: int | None = None,
        pitch_mm: Any = None,
        sad_mm: float = SAD_MM,
        sdd_mm: float = SDD_MM,
        phantom: Any = "A",
        seed: int = 0,
        detector_model: Any = None,
        beam: Any = None,
        readout_s: float = 0.0,
        follow: dict[str, str] | None = None,
    ) -> None:
        """``follow``: the URIs of a bench's ``hexapod``, ``rotation_stage`` and ``xray`` in other processes, whose
        pose and exposures this panel's world takes (:func:`devices.twins.feed.follow_bench`)."""
        super().__init__()
        self.follow = dict(follow) if follow else None
        self.world = world if world is not None else get_world("bench")
        cols = rows if cols is None else cols
        rows, cols = int(rows), int(cols)
        if pitch_mm is None:  # the reference panel read out at this size
            pitch = (reference_panel(cols).pitch_col, reference_panel(rows).pitch_row)
        else:  # one pitch, "col,row" text or a pair
            parts = [float(v) for v in (pitch_mm.split(",") if isinstance(pitch_mm, str) else np.atleast_1d(pitch_mm))]
            pitch = (parts[0], parts[-1])
        self.panel = Panel(rows, cols, *pitch)
        self.sad_mm, self.sdd_mm = float(sad_mm), float(sdd_mm)
        self.binning = 1
        self.mode = "SOFTWARE"
        self.armed = False
        self.seed = int(seed)  # frame noise and, for a phantom given by name, its random layout
        self.rng = np.random.default_rng(self.seed)
        self.detector_model = detector_model
        self.beam = beam  # an orbitct.simulator.Beam: polychromatic images (None: one energy)
        self._renderer: Renderer | None = None
        self._renderer_lock = threading.Lock()
        self._phantom_spec = phantom
        self._seen_exposures = 0
        self._rendering: asyncio.Task[Any] | None = None
        self.rendering = 0  # frames taken whose pixels are still being rendered
        self.readout_s = float(
            readout_s
        )  # hazard on request: a slow panel delivers each frame this long after taking it

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

                phantom = experiment_phantom(phantom, seed=self.seed)
            self._renderer = simulator_renderer(phantom, self.detector_model, self.beam)
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
        except Exception as exc:  # noqa: BLE001 - reported to the client at FRAME?, not lost in a background task
            data, failure = None, f"frame {number} could not be rendered: {exc}"
        if previous is not None:
            await asyncio.wait([previous])  # frames leave in the order they were taken
        late = taken + self.readout_s - time.time()
        if late > 0:
            await asyncio.sleep(late)
        self.rendering -= 1
        if data is None:
            assert self.frames is not None
            self.frames.put_nowait(failure)
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
        if self.follow is not None:
            self.spawn(
                follow_bench(
                    self.world,
                    hexapod_uri=self.follow["hexapod"],
                    stage_uri=self.follow["rotation_stage"],
                    xray_uri=self.follow["xray"],
                )
            )
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
        factor = int_arg(args, 0)
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

    def restart_noise(self) -> None:
        """Draw the frames' noise afresh from the twin's seed: a scan on the twins is the same whatever ran before it
        in the process (the panel's lag, like a real panel's, still carries the last frame over)."""
        self.rng = np.random.default_rng(self.seed)

    def cmd_arm(self, args: list[str]) -> str:
        """``ARM``: discard queued frames, accept triggers; the noise starts afresh (:meth:`restart_noise`)."""
        self.restart_noise()
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
            raise CommandError(
                ERR_NOT_ARMED,
                f"software trigger needs an armed panel in SOFTWARE mode (armed={int(self.armed)}, mode={self.mode})",
            )
        return str(self.start_frame("projection", *self._settings()))

    def cmd_dark(self, args: list[str]) -> str:
        """``DARK``: take a dark frame; answers its number."""
        return str(self.start_frame("dark", 0.0, 0.0, self._settings()[2]))

    def cmd_flat(self, args: list[str]) -> str:
        """``FLAT``: take an open-beam frame; answers its number."""
        return str(self.start_frame("flat", *self._settings()))
