"""Rotations helpers and bench kinematics round trips."""

import numpy as np
import pytest

from orbitct.kinematics import (
    STACK_ORDERS,
    hexapod_pose_from_transform,
    hexapod_transform,
    object_pose,
    split_pose,
)
from orbitct.rotations import (
    matrix_to_rotvec,
    rot_x,
    rot_xyz,
    rot_y,
    rot_z,
    rotvec_to_matrix,
    similarity_fit,
    xyz_angles,
)

RNG = np.random.default_rng(11)


def test_elementary_rotations_are_right_handed() -> None:
    assert np.allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1])
    assert np.allclose(rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0])


def test_xyz_angles_round_trip() -> None:
    a = RNG.uniform(-1.2, 1.2, (50, 3))
    assert np.allclose(xyz_angles(rot_xyz(a[:, 0], a[:, 1], a[:, 2])), a, atol=1e-12)


def test_rotvec_round_trip() -> None:
    r = RNG.normal(size=(50, 3))
    r *= (RNG.uniform(1e-10, 3.0, 50) / np.linalg.norm(r, axis=1))[:, None]
    assert np.allclose(matrix_to_rotvec(rotvec_to_matrix(r)), r, atol=1e-9)
    R = rotvec_to_matrix(r)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)


def test_similarity_fit_recovers_transform() -> None:
    src = RNG.normal(size=(10, 3)) * 50
    R = rotvec_to_matrix([0.2, -0.4, 0.1])
    dst = 1.03 * src @ R.T + [1.0, 2.0, 3.0]
    s, R2, t = similarity_fit(src, dst)
    assert np.isclose(s, 1.03) and np.allclose(R2, R) and np.allclose(t, [1, 2, 3])
    with pytest.raises(ValueError, match="at least 3"):
        similarity_fit(src[:2], dst[:2])


@pytest.mark.parametrize("order", STACK_ORDERS)
def test_kinematics_round_trip(order: str) -> None:
    pivot = (3.0, -5.0, 120.0)
    stage = RNG.uniform(-np.pi, np.pi, 20)
    hexa = np.concatenate([RNG.uniform(-10, 10, (20, 3)), RNG.uniform(-0.4, 0.4, (20, 3))], axis=1)
    R, t = object_pose(stage, hexa, order=order, pivot=pivot)
    assert np.allclose(split_pose(R, t, stage, order=order, pivot=pivot), hexa, atol=1e-9)


def test_hexapod_transform_inverse_and_pivot() -> None:
    pose = np.array([1.0, 2.0, 3.0, 0.1, -0.2, 0.3])
    pivot = np.array([0.0, 0.0, 50.0])
    R, t = hexapod_transform(pose, pivot)
    # the pivot point only moves by the translation part
    assert np.allclose(R @ pivot + t, pivot + pose[:3])
    assert np.allclose(hexapod_pose_from_transform(R, t, pivot), pose)


def test_unknown_stack_order() -> None:
    with pytest.raises(ValueError, match="stack order must be one of"):
        object_pose(0.0, np.zeros(6), order="sideways")
