"""Orbit shapes, frame counts, parameter validation, waypoint files."""

from pathlib import Path

import numpy as np
import pytest

from orbitct.geometry import Panel, ViewGeometry
from orbitct.orbits import ORBIT_KINDS, OrbitError, make_orbit, orbit_from_json

DET = Panel(32, 32, 427 / 32, 427 / 32)


def test_circular_covers_full_turn_without_duplicate() -> None:
    o = make_orbit("circular", n_frames=360)
    assert o.n_frames == 360
    assert np.allclose(np.diff(o.theta_deg), 1.0) and o.theta_deg[0] == 0 and np.isclose(o.theta_deg[-1], 359.0)
    assert np.all(o.phi == 0)


def test_sawtooth_shape() -> None:
    o = make_orbit("sawtooth", n_frames=500)
    assert o.n_frames == 500
    # rotation covers 360 degrees at constant speed
    assert np.allclose(np.diff(o.theta_deg), 360 / 500)
    # tilt within +-20, reaching it to within one step, at constant speed
    step = 4 * 20 * 2 / 500
    assert np.abs(o.phi_deg).max() <= 20 + 1e-9 and np.abs(o.phi_deg).max() >= 20 - step
    d = np.diff(o.phi_deg)
    assert np.abs(d).max() <= step + 1e-9 and np.isclose(np.median(np.abs(d)), step)
    # two full cycles: four turning points
    sgn = np.sign(d[np.abs(d) > 1e-9])
    assert np.sum(sgn[1:] != sgn[:-1]) == 4
    rot, tilt = o.step_sizes()
    assert np.isclose(np.degrees(rot), 0.72) and np.isclose(np.degrees(tilt), step, rtol=0.02)


def test_dcarc_shape_and_frame_split() -> None:
    o = make_orbit("dcarc", n_frames=777)
    seg = o.segment
    assert o.n_segments == 3
    # frames proportional to angular length: 360 + 360 + 57 degrees
    counts = np.bincount(seg)
    assert counts.sum() == 777 and np.allclose(counts, [360, 360, 57], atol=1)
    assert np.allclose(o.phi_deg[seg == 0], 25) and np.allclose(o.phi_deg[seg == 1], -25)
    for s in (0, 1):
        assert np.ptp(o.theta_deg[seg == s]) > 357
    arc = seg == 2
    assert np.allclose(o.theta_deg[arc], 0.0)
    assert np.isclose(o.phi_deg[arc][0], 29) and np.isclose(o.phi_deg[arc][-1], -28)


def test_multiarc_pheno_preset() -> None:
    o = make_orbit("multiarc", preset="pheno")
    assert o.n_frames == 857 and o.n_segments == 4
    seg = o.segment
    assert np.allclose(o.phi_deg[seg == 0], 10) and np.allclose(o.phi_deg[seg == 1], 10)
    assert np.allclose(o.phi_deg[seg == 2], -20)
    assert np.isclose(np.ptp(o.theta_deg[seg == 0]), 120) and np.isclose(np.ptp(o.theta_deg[seg == 2]), 120)
    # the two +10 degree arcs together cover 210 degrees
    both = o.theta_deg[seg <= 1]
    assert np.isclose(both.max() - both.min(), 210)
    tilt_arc = o.phi_deg[seg == 3]
    assert np.isclose(tilt_arc.min(), -25) and np.isclose(tilt_arc.max(), 30)
    assert np.ptp(o.theta_deg[seg == 3]) == 0


def test_multiarc_custom_arcs() -> None:
    arcs = [
        {"kind": "rotation", "tilt_deg": 5, "start_deg": 0, "end_deg": 90},
        {"kind": "tilt", "rotation_deg": 45, "start_deg": -30, "end_deg": 0},
    ]
    o = make_orbit("multiarc", n_frames=120, arcs=arcs)
    assert np.bincount(o.segment).tolist() == [90, 30]


def test_waypoints_csv_and_yaml(tmp_path: Path) -> None:
    csv = tmp_path / "w.csv"
    csv.write_text("rotation_deg,tilt_deg\n0,0\n90,10\n180,-10\n")
    yml = tmp_path / "w.yaml"
    yml.write_text("waypoints:\n  - {rotation_deg: 0, tilt_deg: 0}\n  - [90, 10]\n  - [180, -10]\n")
    a = make_orbit("waypoints", path=str(csv), n_frames=101)
    b = make_orbit("waypoints", path=str(yml), n_frames=101)
    assert np.allclose(a.theta, b.theta) and np.allclose(a.phi, b.phi)
    assert np.isclose(a.theta_deg[0], 0) and np.isclose(a.theta_deg[-1], 180) and np.isclose(a.phi_deg[-1], -10)
    # constant angular speed along the polyline
    step = np.hypot(np.diff(a.theta_deg), np.diff(a.phi_deg))
    assert np.allclose(step, step.mean(), rtol=0.05)
    # the params carry the points, so the orbit rebuilds without the file
    csv.unlink()
    assert np.allclose(orbit_from_json(a.to_json()).theta, a.theta)


@pytest.mark.parametrize("name", sorted(ORBIT_KINDS))
def test_params_rebuild_the_same_orbit(name: str) -> None:
    kw = {"multiarc": {"preset": "pheno"}, "waypoints": {"points": [[0, 0], [100, 20]]}}.get(name, {})
    o = make_orbit(name, n_frames=40, **kw)
    o2 = make_orbit(o.name, **o.params)
    assert np.array_equal(o.theta, o2.theta) and np.array_equal(o.phi, o2.phi)
    with pytest.raises(ValueError):
        o.theta[0] = 1.0  # immutable


def test_nominal_geometry_matches_bench_poses() -> None:
    o = make_orbit("sawtooth", n_frames=30)
    g = o.nominal_geometry(785.0, 1200.0, DET)
    lab = ViewGeometry.from_carm(0, 0, 785.0, 1200.0, DET)
    assert g.allclose(ViewGeometry.from_object_poses(lab, *o.poses()), atol_mm=1e-9)


@pytest.mark.parametrize(
    "name, params, message",
    [
        ("circular", {"n_frames": 1}, "n_frames: Input should be greater than or equal to 2"),
        ("circular", {"n_frames": 10**6}, "n_frames: Input should be less than or equal to 20000"),
        ("circular", {"tilt_deg": 75}, "tilt_deg: Input should be less than or equal to 60"),
        ("circular", {"range_deg": 0}, "range_deg must be non-zero"),
        ("sawtooth", {"amplitude_deg": 61}, "amplitude_deg: Input should be less than or equal to 60"),
        ("sawtooth", {"speed": 2}, "speed: Extra inputs are not permitted"),
        ("dcarc", {"arc_start_deg": 10, "arc_end_deg": 10}, "arc_start_deg and arc_end_deg must differ"),
        ("multiarc", {}, "give exactly one of 'preset'"),
        ("multiarc", {"preset": "zeego"}, "preset: Input should be 'pheno'"),
        ("multiarc", {"arcs": [{"kind": "wobble"}]}, "arcs.0"),
        ("multiarc", {"n_frames": 5, "preset": "pheno"}, "at least 2 per arc"),
        ("waypoints", {}, "give 'path'"),
        ("waypoints", {"path": "/no/such/file.csv"}, "does not exist"),
        ("waypoints", {"points": [[0, 0], [10, 90]]}, "less than or equal to 60"),
        ("helix", {}, "unknown orbit 'helix'; known orbits are"),
        ("sawtooth", {"start_deg": float("nan")}, "start_deg: Input should be a finite number"),
        ("circular", {"range_deg": float("inf")}, "range_deg: Input should be a finite number"),
    ],
)
def test_validation_errors_are_clear(name: str, params: dict, message: str) -> None:
    with pytest.raises(OrbitError, match=message.replace("(", r"\(").replace(")", r"\)")) as exc:
        make_orbit(name, **params)
    if name in ORBIT_KINDS:
        assert "parameters:" in str(exc.value) or "does not exist" in str(exc.value)


def test_bad_waypoint_file(tmp_path: Path) -> None:
    p = tmp_path / "bad.csv"
    p.write_text("angle,tilt\n1,2\n3,4\n")
    with pytest.raises(OrbitError, match="header must be 'rotation_deg,tilt_deg'"):
        make_orbit("waypoints", path=str(p))
    p.write_text("rotation_deg,tilt_deg\n1,x\n3,4\n")
    with pytest.raises(OrbitError, match="line 1"):
        make_orbit("waypoints", path=str(p))
    q = tmp_path / "one.yaml"
    q.write_text("- [0, 0]\n")
    with pytest.raises(OrbitError, match="at least 2 waypoints"):
        make_orbit("waypoints", path=str(q))
