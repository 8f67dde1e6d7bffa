"""Inverse kinematics: nominal view + error -> stage + hexapod, and back (commanded pose -> view -> pose)."""

from __future__ import annotations

import numpy as np
import pytest

from acquire.config import StackConfig, parse_config
from acquire.kinematics import (
    bench_axes,
    errors_from_axes,
    hexapod_from_user,
    hexapod_to_user,
    target_object_pose,
    views_from_axes,
)
from orbitct.geometry import ViewGeometry

STACKS = [
    StackConfig(),
    StackConfig(pivot_mm=(0.0, 0.0, 40.0)),
    StackConfig(order="hexapod_on_stage", pivot_mm=(5.0, -3.0, 20.0)),
]


def _orbit(n: int = 25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    theta = np.linspace(0, 2 * np.pi, n, endpoint=False)
    phi = np.radians(20) * np.sin(2 * theta)
    err = np.concatenate([rng.normal(0, 0.01, (n, 3)), rng.normal(0, 3.0, (n, 3))], axis=1)
    return theta, phi, err


@pytest.mark.parametrize("stack", STACKS)
def test_error_free_axes_give_nominal_views(stack: StackConfig) -> None:
    cfg = parse_config({"geometry": {"detector": {"rows": 64, "cols": 64}}})
    theta, phi, _ = _orbit()
    stage, hexapod = bench_axes(theta, phi, None, stack)
    views = views_from_axes(stage, hexapod, cfg.geometry.lab_view(), stack)
    assert views.allclose(cfg.geometry.carm_views(theta, phi), atol_mm=1e-9)
    np.testing.assert_allclose(stage, -theta)


def test_stage_on_hexapod_splits_rotation_and_tilt() -> None:
    theta, phi, _ = _orbit()
    stage, hexapod = bench_axes(theta, phi)
    np.testing.assert_allclose(hexapod[:, 3], phi, atol=1e-12)  # U carries the tilt
    np.testing.assert_allclose(hexapod[:, [0, 1, 2, 4, 5]], 0.0, atol=1e-12)


@pytest.mark.parametrize("stack", STACKS)
def test_round_trip_with_errors(stack: StackConfig) -> None:
    cfg = parse_config({"geometry": {"detector": {"rows": 64, "cols": 64}}})
    theta, phi, err = _orbit()
    stage, hexapod = bench_axes(theta, phi, err, stack)
    np.testing.assert_allclose(errors_from_axes(stage, hexapod, theta, phi, stack), err, atol=1e-10)
    views = views_from_axes(stage, hexapod, cfg.geometry.lab_view(), stack)
    R, t = target_object_pose(theta, phi, err)
    expected = ViewGeometry.from_object_poses(cfg.geometry.lab_view(), R, t)
    assert views.allclose(expected, atol_mm=1e-9)
    assert not views.allclose(cfg.geometry.carm_views(theta, phi), atol_mm=0.1)


def test_user_units_round_trip() -> None:
    q = np.array([1.0, -2.0, 3.0, 0.1, -0.2, 0.3])
    user = hexapod_to_user(q)
    assert user["U"] == pytest.approx(np.degrees(0.1)) and user["X"] == 1.0
    np.testing.assert_allclose(hexapod_from_user(user), q)


def test_injected_errors_follow_errorprofiles_definition() -> None:
    from orbitct.errorprofiles import make_profile
    from orbitct.orbits import make_orbit

    cfg = parse_config({"geometry": {"detector": {"rows": 64, "cols": 64}}})
    orbit = make_orbit("sawtooth", n_frames=30)
    rigid = make_profile("bench", seed=3).sample(orbit)
    stage, hexapod = bench_axes(orbit.theta, orbit.phi, rigid.as_array())
    views = views_from_axes(stage, hexapod, cfg.geometry.lab_view())
    nominal = cfg.geometry.carm_views(orbit.theta, orbit.phi)
    assert views.allclose(rigid.apply_to_geometry(nominal), atol_mm=1e-9)
