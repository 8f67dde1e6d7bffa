"""Simulate a complete scan file: darks, flats and projections of a phantom along an orbit with motion errors."""

from __future__ import annotations

import os
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orbitct.errorprofiles import ErrorProfile, RigidErrors, make_profile
from orbitct.geometry import ViewGeometry
from orbitct.orbits import Orbit, OrbitError, make_orbit
from orbitct.phantoms.experiments import experiment_phantom
from orbitct.phantoms.phantom import Phantom
from orbitct.progress import ProgressCallback, report
from orbitct.reference_bench import reference_panel
from orbitct.scanfile import ScanWriter
from orbitct.simulator.beam import Beam
from orbitct.simulator.bench import SimulatedBench
from orbitct.simulator.detector import DetectorModel
from orbitct.simulator.projector import line_integrals

# Orbit each experiment was acquired with in the paper.
DEFAULT_ORBITS: dict[str, tuple[str, dict[str, Any]]] = {
    "A": ("sawtooth", {}),
    "B": ("dcarc", {}),
    "C": ("multiarc", {"preset": "pheno"}),
}
AXES = {"orbit.rotation": "deg", "orbit.tilt": "deg"}
_FLUSH_EVERY = 8


class _BackgroundAppender:
    """Appends frames to a :class:`ScanWriter` on a second thread, so HDF5 I/O overlaps rendering."""

    def __init__(self, writer: ScanWriter) -> None:
        self._w = writer
        self._q: queue.Queue[tuple[Any, ...] | None] = queue.Queue(maxsize=6)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="scan-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            if self._error is not None:
                continue
            args, kwargs = item
            try:
                self._w.append(*args, **kwargs)
            except BaseException as exc:  # noqa: BLE001 - re-raised on the calling thread
                self._error = exc

    def append(self, *args: Any, **kwargs: Any) -> None:
        if self._error is not None:
            raise self._error
        self._q.put((args, kwargs))

    def close(self, raise_error: bool = True) -> None:
        """Wait for every queued frame; re-raise a write error (unless told not to)."""
        self._q.put(None)
        self._thread.join()
        if raise_error and self._error is not None:
            raise self._error


@dataclass(frozen=True)
class SimulationResult:
    """What :func:`simulate_scan` wrote."""

    path: Path
    n_frames: int
    n_projections: int
    elapsed_s: float
    orbit: Orbit
    phantom: Phantom
    errors: RigidErrors

    @property
    def frames_per_s(self) -> float:
        """Projection frames simulated per second (all frames counted)."""
        return self.n_frames / self.elapsed_s if self.elapsed_s > 0 else float("inf")


def resolve_orbit(experiment: str, orbit: str | Orbit | None, n_frames: int | None, **params: Any) -> Orbit:
    """The orbit to simulate: an :class:`Orbit`, a name, or the experiment's default orbit.

    The default orbit's parameters (e.g. C's ``preset=pheno``) apply only when no ``params`` are given.
    """
    if isinstance(orbit, Orbit):
        if n_frames is not None and n_frames != orbit.n_frames:
            raise OrbitError(f"n_frames={n_frames} disagrees with the given orbit's {orbit.n_frames} frames")
        return orbit
    default_name, default_params = DEFAULT_ORBITS.get(str(experiment).upper(), ("sawtooth", {}))
    name = orbit or default_name
    p = dict(default_params) if name == default_name and not params else dict(params)
    if n_frames is not None:
        p["n_frames"] = int(n_frames)
    return make_orbit(name, **p)


def resolve_errors(errors: str | ErrorProfile | None, seed: int) -> ErrorProfile:
    """An error profile from a name (``bench``, ``none``, ``custom``) or as given."""
    if errors is None:
        return make_profile("none", seed)
    return errors if isinstance(errors, ErrorProfile) else make_profile(str(errors), seed)


def _write_true_errors(path: Path, rigid: RigidErrors, n_cal: int) -> None:
    """Store the per-frame errors as ``/truth/errors/{angles_rad, shift_mm}`` (NaN rows for darks and flats)."""
    from orbitct.scanfile import ScanFile

    pad = np.full((n_cal, 3), np.nan)
    with ScanFile(path, mode="r+") as f:
        g = f.h5.require_group("truth/errors")
        g.attrs["convention"] = (
            "lab frame about the nominal isocenter, applied after the nominal pose; "
            "angles = pitch (x), roll (y), yaw (z); R = R_x(pitch) R_y(roll) R_z(yaw)"
        )
        for name, data in (("angles_rad", rigid.angles), ("shift_mm", rigid.shift_mm)):
            if name in g:
                del g[name]
            g.create_dataset(name, data=np.concatenate([pad, data]))


def simulate_scan(
    experiment: str | Phantom,
    orbit: str | Orbit | None = None,
    *,
    out: str | os.PathLike[str],
    n_frames: int | None = None,
    detector_px: int = 768,
    pitch_mm: float | None = None,
    errors: str | ErrorProfile | None = "bench",
    seed: int = 0,
    n_dark: int = 10,
    n_flat: int = 10,
    frame_interval_s: float = 1.0 / 15.0,
    bench: SimulatedBench | None = None,
    detector: str | DetectorModel = "clean",
    beam: str | Beam | None = "mono",
    overwrite: bool = False,
    progress: ProgressCallback | None = None,
) -> SimulationResult:
    """Write a complete simulated scan file to ``out`` and return what was made.

    Frames: ``n_dark`` darks, ``n_flat`` flats, then one projection per orbit frame rendered at
    the *true* pose (nominal pose with the profile's errors, ``orbitct.errorprofiles``). The file
    holds the nominal geometry, the true geometry, true marker centres and the phantom under
    ``/truth``. ``seed`` sets the phantom's random layout, the errors and the noise. ``detector``: the panel's
    model or a preset's name (:meth:`DetectorModel.preset`: ``clean``, ``realistic``), unless ``bench`` gives one;
    ``beam``: one energy (``mono``) or a spectrum (``polychromatic`` or a :class:`Beam`), unless ``bench`` gives one.
    """
    t0 = time.perf_counter()
    if n_dark < 0 or n_flat < 0:
        raise ValueError(f"n_dark and n_flat must be >= 0, got {n_dark}, {n_flat}")
    phantom = experiment if isinstance(experiment, Phantom) else experiment_phantom(experiment, seed)
    exp_name = phantom.name if isinstance(experiment, Phantom) else str(experiment).upper()
    orb = resolve_orbit(exp_name, orbit, n_frames)
    profile = resolve_errors(errors, seed)
    model = DetectorModel.preset(detector) if isinstance(detector, str) else detector
    spectrum = Beam.preset(beam) if isinstance(beam, str) else beam
    bench = bench or SimulatedBench(panel=reference_panel(detector_px, pitch_mm), model=model, beam=spectrum)
    det = bench.panel
    rigid = profile.sample(orb)
    R_true, t_true = rigid.true_poses(*orb.poses())
    true_geom = ViewGeometry.from_object_poses(bench.lab_view, R_true, t_true)
    nominal = bench.nominal_geometry(orb)
    n_cal = n_dark + n_flat
    total = n_cal + orb.n_frames
    rng = np.random.default_rng([seed, 99])
    config = {**bench.config(), "simulation": {"experiment": exp_name, "seed": seed, "errors": profile.to_json()}}
    with ScanWriter(
        out,
        det,
        axes=AXES,
        orbit_name=orb.name,
        orbit_params=orb.params,
        config=config,
        marker_diameter_mm=phantom.marker_diameter_mm,
        overwrite=overwrite,
    ) as w:
        w.write_truth(
            np.concatenate([np.full((n_cal, 12), np.nan), true_geom.vectors]), phantom.markers_xyz, phantom.to_json()
        )
        w.set_attrs(
            "simulation",
            experiment=exp_name,
            seed=int(seed),
            errors=profile.to_json(),
            errors_peak=rigid.summary(),
            frame_interval_s=frame_interval_s,
        )
        bg = _BackgroundAppender(w)
        done = 0
        try:
            for _ in range(n_dark):
                bg.append(bench.model.dark(rng, det.shape), "dark", done * frame_interval_s)
                done += 1
            for _ in range(n_flat):
                bg.append(bench.model.flat(rng, det.shape, det.mean_pitch_mm), "flat", done * frame_interval_s)
                done += 1
            report(progress, "simulate", done, total, "dark and flat frames")
            th, ph = orb.theta_deg, orb.phi_deg
            for i in range(orb.n_frames):
                li = line_integrals(phantom, true_geom, i, beam=bench.beam)
                cmd = {"orbit.rotation": float(th[i]), "orbit.tilt": float(ph[i])}
                last = i == orb.n_frames - 1
                bg.append(
                    bench.model.expose(li, rng, det.mean_pitch_mm),
                    "projection",
                    done * frame_interval_s,
                    nominal_vector=nominal.vectors[i],
                    commanded=cmd,
                    flush=last or i % _FLUSH_EVERY == 0,
                )
                done += 1
                if progress is not None and (i % 5 == 4 or last):
                    el = time.perf_counter() - t0
                    report(progress, "simulate", done, total, f"projection {i + 1}/{orb.n_frames}", fps=done / el)
        except BaseException:
            bg.close(raise_error=False)
            raise
        bg.close()
    _write_true_errors(Path(out), rigid, n_cal)
    return SimulationResult(Path(out), total, orb.n_frames, time.perf_counter() - t0, orb, phantom, rigid)
