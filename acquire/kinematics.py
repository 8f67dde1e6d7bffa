"""Bench inverse kinematics: nominal view + injected error -> rotation-stage angle + hexapod pose, and back.

An injected error is a 6-vector ``(pitch, roll, yaw, x, y, z)`` (rad, mm): the rigid lab-frame
transform of ``orbitct.errorprofiles`` about the nominal isocenter, applied after the ideal pose
of ``geometry.md``: ``R = R_x(pitch) R_y(roll) R_z(yaw) R_ideal(theta, phi)``, ``t = (x, y, z)``.
The stage carries the rotation (``stage = -theta``); the hexapod carries the tilt and
the errors, about its pivot (``orbitct.kinematics.split_pose``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from acquire.config import StackConfig
from orbitct.geometry import ViewGeometry, ideal_bench_pose
from orbitct.kinematics import object_pose, split_pose
from orbitct.rotations import rot_xyz

HEXAPOD_AXES: tuple[str, ...] = ("X", "Y", "Z", "U", "V", "W")
HEXAPOD_UNITS: tuple[str, ...] = ("mm", "mm", "mm", "deg", "deg", "deg")
STAGE_AXIS = "rotation_stage.R"  # the rotation stage's one axis, as recorded in /frames/commanded


def _errors(errors: ArrayLike | None, n: int) -> NDArray[np.float64]:
    if errors is None:
        return np.zeros((n, 6))
    e = np.asarray(errors, dtype=float)
    return np.broadcast_to(e, (n, 6)).copy()


def target_object_pose(
    theta: ArrayLike, phi: ArrayLike, errors: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Object poses ``(R (N,3,3), t (N,3))`` for nominal views with injected errors added."""
    th, ph = np.broadcast_arrays(np.atleast_1d(np.asarray(theta, float)), np.atleast_1d(np.asarray(phi, float)))
    e = _errors(errors, th.shape[0])
    R = rot_xyz(e[:, 0], e[:, 1], e[:, 2]) @ ideal_bench_pose(th, ph)
    return R, e[:, 3:6].copy()


def bench_axes(
    theta: ArrayLike, phi: ArrayLike, errors: ArrayLike | None = None, stack: StackConfig = StackConfig()
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Commanded stage angles (N,) rad and hexapod poses (N, 6) mm/rad for nominal views plus errors."""
    R, t = target_object_pose(theta, phi, errors)
    stage = -np.atleast_1d(np.asarray(theta, dtype=float)) * np.ones(R.shape[0])
    hexapod = split_pose(R, t, stage, order=stack.order, pivot=stack.pivot_mm)
    return stage, hexapod


def views_from_axes(
    stage: ArrayLike, hexapod: ArrayLike, lab_view: ViewGeometry, stack: StackConfig = StackConfig()
) -> ViewGeometry:
    """Forward kinematics: the views (object frame) that stage angles and hexapod poses produce."""
    R, t = object_pose(
        np.atleast_1d(np.asarray(stage, float)),
        np.atleast_2d(np.asarray(hexapod, float)),
        order=stack.order,
        pivot=stack.pivot_mm,
    )
    return ViewGeometry.from_object_poses(lab_view, R, t)


def errors_from_axes(
    stage: ArrayLike, hexapod: ArrayLike, theta: ArrayLike, phi: ArrayLike, stack: StackConfig = StackConfig()
) -> NDArray[np.float64]:
    """Reverse of :func:`bench_axes`: the injected errors (N, 6) that axes realise for given nominal views."""
    from orbitct.rotations import xyz_angles

    R, t = object_pose(
        np.atleast_1d(np.asarray(stage, float)),
        np.atleast_2d(np.asarray(hexapod, float)),
        order=stack.order,
        pivot=stack.pivot_mm,
    )
    Ri = ideal_bench_pose(np.atleast_1d(np.asarray(theta, float)), np.atleast_1d(np.asarray(phi, float)))
    Re = R @ np.swapaxes(Ri, -1, -2)
    return np.concatenate([xyz_angles(Re), t], axis=-1)


def hexapod_to_user(pose: ArrayLike) -> dict[str, float]:
    """Hexapod pose (mm, rad) as controller targets ``{'X': mm, ..., 'U': deg, ...}``."""
    q = np.asarray(pose, dtype=float)
    return {a: float(q[i]) if i < 3 else float(np.degrees(q[i])) for i, a in enumerate(HEXAPOD_AXES)}


def hexapod_from_user(values: dict[str, float]) -> NDArray[np.float64]:
    """Inverse of :func:`hexapod_to_user`."""
    return np.array([values[a] if i < 3 else np.radians(values[a]) for i, a in enumerate(HEXAPOD_AXES)], dtype=float)
