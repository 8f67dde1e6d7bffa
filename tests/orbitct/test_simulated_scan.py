"""simulate_scan: complete files for every experiment, truth consistent with the errors, aborts recorded."""

from pathlib import Path

import numpy as np
import pytest

from orbitct.errorprofiles import make_profile
from orbitct.orbits import make_orbit
from orbitct.progress import ProgressEvent
from orbitct.scanfile import ScanFile
from orbitct.simulator import SimulatedBench, simulate_scan


@pytest.mark.parametrize("experiment, orbit", [("A", "sawtooth"), ("B", "dcarc"), ("C", "multiarc")])
def test_every_experiment_makes_a_complete_scan(tmp_path: Path, experiment: str, orbit: str) -> None:
    events: list[ProgressEvent] = []
    res = simulate_scan(
        experiment,
        out=tmp_path / "s.h5",
        n_frames=8,
        detector_px=48,
        n_dark=1,
        n_flat=2,
        seed=2,
        progress=events.append,
    )
    assert res.orbit.name == orbit and res.n_frames == 11 and res.frames_per_s > 0
    assert events[-1].done == events[-1].total == 11
    with ScanFile(res.path) as f:
        assert f.status == "complete" and f.n_frames == 11
        assert f.image_key.tolist() == [2, 1, 1] + [0] * 8
        truth, nominal = f.geometry("truth"), f.geometry("nominal")
        assert truth[3:].allclose(res.errors.apply_to_geometry(nominal[3:]), atol_mm=1e-9)
        assert np.allclose(f.truth_markers_xyz(), res.phantom.markers_xyz)
        assert f.phantom["name"] == experiment
        assert f.frames.dtype == np.uint16
        assert np.allclose(f.h5["truth/errors/shift_mm"][3:], res.errors.shift_mm)
        assert np.isnan(f.h5["truth/errors/angles_rad"][:3]).all()


def test_markers_stay_on_the_detector_for_experiment_a() -> None:
    """Over the whole sawtooth orbit with bench errors every BB of phantom A projects onto the panel."""
    from orbitct.phantoms import experiment_phantom

    bench = SimulatedBench.with_panel(128)
    o = make_orbit("sawtooth", n_frames=200)
    e = make_profile("bench", seed=0).sample(o)
    g = bench.view(*e.true_poses(*o.poses()))
    uv = g.project(experiment_phantom("A", 0).markers_xyz)
    margin = 3.17 / 2 * bench.magnification / bench.panel.pitch_col
    assert (uv > margin).all() and (uv < 127 - margin).all()


def test_same_seed_same_scan(tmp_path: Path) -> None:
    kw = dict(n_frames=3, detector_px=32, n_dark=1, n_flat=1, seed=9)
    a = simulate_scan("A", out=tmp_path / "a.h5", **kw)
    b = simulate_scan("A", out=tmp_path / "b.h5", **kw)
    with ScanFile(a.path) as fa, ScanFile(b.path) as fb:
        assert np.array_equal(fa.frames[:], fb.frames[:])
        assert fa.geometry("truth").allclose(fb.geometry("truth"), atol_mm=0)


def test_interrupted_simulation_is_marked_aborted(tmp_path: Path) -> None:
    def stop(ev: ProgressEvent) -> None:
        if ev.done >= 7:
            raise KeyboardInterrupt

    path = tmp_path / "x.h5"
    with pytest.raises(KeyboardInterrupt):
        simulate_scan("A", out=path, n_frames=20, detector_px=32, n_dark=1, n_flat=1, progress=stop)
    with ScanFile(path) as f:
        assert f.status == "aborted" and f.status_reason == "interrupted (Ctrl-C)"
        assert 2 <= f.n_frames < 22


def test_resolve_orbit_defaults_and_overrides() -> None:
    from orbitct.orbits import OrbitError
    from orbitct.simulator import resolve_orbit

    assert resolve_orbit("C", None, None).params == {"n_frames": 857, "preset": "pheno"}
    arcs = [{"kind": "tilt", "rotation_deg": 0, "start_deg": -10, "end_deg": 10}]
    assert resolve_orbit("C", "multiarc", 20, arcs=arcs).n_segments == 1
    assert resolve_orbit("B", None, 30).name == "dcarc"
    orb = make_orbit("circular", n_frames=10)
    assert resolve_orbit("A", orb, None) is orb
    with pytest.raises(OrbitError, match="disagrees"):
        resolve_orbit("A", orb, 11)
