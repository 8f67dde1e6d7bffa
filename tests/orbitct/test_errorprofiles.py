"""Error profiles: statistics match their definition, seeding, composition, where errors apply."""

import numpy as np
import pytest

from orbitct.errorprofiles import (
    ErrorProfileError,
    RigidErrors,
    compose,
    make_profile,
    profile_from_json,
)
from orbitct.geometry import Panel, ViewGeometry
from orbitct.orbits import make_orbit
from orbitct.rotations import rot_x, rot_y, rot_z

DET = Panel(32, 32, 427 / 32, 427 / 32)


def _sine_fit(phase_of: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    """Amplitude of the best sine in ``phase_of`` plus the residual."""
    A = np.stack([np.sin(phase_of), np.cos(phase_of)], axis=1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return float(np.hypot(*coef)), y - A @ coef


def test_bench_profile_statistics() -> None:
    o = make_orbit("sawtooth", n_frames=4000)
    prof = make_profile("bench", seed=5)
    e = prof.sample(o)
    rot, tilt = o.step_sizes()
    A = prof.amplitudes(o)
    assert np.allclose(A, [tilt, max(rot, tilt), rot])  # pitch, roll, yaw
    for k in range(3):
        ang = e.angles[:, k]
        assert np.abs(ang).max() <= A[k] + 1e-15
        amp, res = _sine_fit(o.theta, ang)
        assert amp == pytest.approx(0.5 * A[k], rel=0.05)  # the sag sine: half the amplitude
        assert np.abs(res).max() <= 0.5 * A[k] * 1.05  # uniform noise within the other half
        assert res.std() == pytest.approx(0.5 * A[k] / np.sqrt(3), rel=0.05)
    s = 2 * np.pi * np.arange(o.n_frames) / o.n_frames
    for k in range(3):
        amp, res = _sine_fit(s, e.shift_mm[:, k])
        assert amp == pytest.approx(8.0, abs=0.1)
        assert np.abs(res).max() <= 2.1 and res.std() == pytest.approx(2 / np.sqrt(3), rel=0.05)


def test_bench_circular_orbit_borrows_rotation_step() -> None:
    o = make_orbit("circular", n_frames=500)
    A = make_profile("bench").amplitudes(o)
    assert np.allclose(A, np.radians(0.72))


def test_seeded_and_reproducible() -> None:
    o = make_orbit("dcarc", n_frames=100)
    a, b, c = (make_profile("bench", seed=s).sample(o) for s in (1, 1, 2))
    assert np.array_equal(a.angles, b.angles) and np.array_equal(a.shift_mm, b.shift_mm)
    assert not np.allclose(a.shift_mm, c.shift_mm)


def test_none_and_custom() -> None:
    o = make_orbit("circular", n_frames=2000)
    z = make_profile("none").sample(o)
    assert not z.angles.any() and not z.shift_mm.any()
    c = make_profile(
        "custom", seed=3, angle_amplitude_deg=(0.5, 0, 0), angle_cycles=3, shift_noise_mm=(0, 0, 1.5)
    ).sample(o)
    s = 2 * np.pi * 3 * np.arange(2000) / 2000
    amp, res = _sine_fit(s, c.pitch)
    assert amp == pytest.approx(np.radians(0.5), rel=1e-9) and np.abs(res).max() < 1e-12
    assert not c.roll.any() and not c.yaw.any() and not c.shift_mm[:, :2].any()
    assert np.abs(c.shift_mm[:, 2]).max() <= 1.5 and c.shift_mm[:, 2].std() == pytest.approx(1.5 / np.sqrt(3), rel=0.06)


def test_transform_convention() -> None:
    e = RigidErrors([[0.2, 0.1, 0.3]], [[1.0, 2.0, 3.0]])
    R, t = e.transforms()
    assert np.allclose(R[0], rot_x(0.2) @ rot_y(0.1) @ rot_z(0.3))  # R_x(pitch) R_y(roll) R_z(yaw)
    assert np.allclose(t, [[1, 2, 3]])
    back = RigidErrors.from_transforms(R, t)
    assert np.allclose(back.angles, e.angles)


def test_composition_is_transform_product() -> None:
    o = make_orbit("sawtooth", n_frames=50)
    a, b = (
        make_profile("bench", seed=1),
        make_profile("custom", seed=2, angle_amplitude_deg=(1, 2, 3), shift_amplitude_mm=(1, 1, 1)),
    )
    ea, eb = a.sample(o), b.sample(o)
    ec = (a + b).sample(o)
    Ra, ta = ea.transforms()
    Rb, tb = eb.transforms()
    Rc, tc = ec.transforms()
    assert np.allclose(Rc, Rb @ Ra) and np.allclose(tc, np.einsum("nij,nj->ni", Rb, ta) + tb)
    assert np.allclose(compose(a, b, make_profile("none")).sample(o).angles, ec.angles)


def test_apply_to_geometry_equals_bench_true_poses() -> None:
    o = make_orbit("multiarc", n_frames=60, preset="pheno")
    e = make_profile("bench", seed=4).sample(o)
    lab = ViewGeometry.from_carm(0, 0, 785.0, 1200.0, DET)
    truth = ViewGeometry.from_object_poses(lab, *e.true_poses(*o.poses()))
    assert e.apply_to_geometry(o.nominal_geometry(785.0, 1200.0, DET)).allclose(truth, atol_mm=1e-9)
    # a pure lab shift t moves the source by -t in the reference view's object frame
    shift = RigidErrors(np.zeros((1, 3)), [[0.0, 0.0, 5.0]])
    g0 = ViewGeometry.from_carm(0.0, 0.0, 785.0, 1200.0, DET)
    assert np.allclose(shift.apply_to_geometry(g0).S[0], [0, -785, -5])


def test_profile_errors() -> None:
    with pytest.raises(ErrorProfileError, match="unknown error profile 'wobbly'"):
        make_profile("wobbly")
    with pytest.raises(ErrorProfileError, match="sag_fraction"):
        make_profile("bench", sag_fraction=2)
    with pytest.raises(ErrorProfileError, match="takes no parameters"):
        make_profile("none", amplitude=1)
    with pytest.raises(ErrorProfileError, match="cannot compose"):
        RigidErrors.zeros(3).then(RigidErrors.zeros(4))


def test_json_rebuilds_profiles() -> None:
    o = make_orbit("sawtooth", n_frames=40)
    prof = make_profile("bench", seed=7, shift_amplitude_mm=4) + make_profile(
        "custom", seed=1, angle_noise_deg=(1, 0, 0)
    )
    again = profile_from_json(prof.to_json())
    assert np.array_equal(again.sample(o).angles, prof.sample(o).angles)
    assert "BenchProfile" not in repr(prof) and "composed" in repr(prof)
    with pytest.raises(ErrorProfileError, match="needs a 'name'"):
        profile_from_json({"seed": 1})
