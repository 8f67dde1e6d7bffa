"""Bench kinematics: rotation stage angle + hexapod pose <-> object pose (``geometry.md``, Bench).

Conventions (lab frame, origin at the nominal isocenter, z up, source on -y):
- the rotation stage turns about lab +z by ``stage`` (rad);
- the hexapod pose is ``(X, Y, Z, U, V, W)`` (mm, rad); its rotation is PI's
  ``R_h = R_x(U) R_y(V) R_z(W)`` applied about the pivot point ``p`` (mm), so a
  platform point ``x`` goes to ``R_h (x - p) + p + (X, Y, Z)``;
- stack order ``stage_on_hexapod`` (default: the stage sits on the hexapod
  platform) gives ``x_lab = H(R_z(stage) x)``; ``hexapod_on_stage`` gives
  ``x_lab = R_z(stage) H(x)``.
An object pose is ``x_lab = R x_obj + t``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbitct.rotations import rot_xyz, rot_z, xyz_angles

STACK_ORDERS: tuple[str, ...] = ("stage_on_hexapod", "hexapod_on_stage")


def _check_order(order: str) -> None:
    if order not in STACK_ORDERS:
        raise ValueError(f"stack order must be one of {STACK_ORDERS}, got {order!r}")


def hexapod_transform(
    pose: ArrayLike, pivot: ArrayLike = (0.0, 0.0, 0.0)
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rigid transform ``(R, t)`` of hexapod pose(s) ``(..., 6)`` = X, Y, Z (mm), U, V, W (rad)."""
    q = np.asarray(pose, dtype=float)
    p = np.asarray(pivot, dtype=float)
    R = rot_xyz(q[..., 3], q[..., 4], q[..., 5])
    t = q[..., :3] + p - np.einsum("...ij,j->...i", R, p)
    return R, t


def hexapod_pose_from_transform(R: ArrayLike, t: ArrayLike, pivot: ArrayLike = (0.0, 0.0, 0.0)) -> NDArray[np.float64]:
    """Inverse of :func:`hexapod_transform`: pose(s) ``(..., 6)`` (mm, rad)."""
    Rm = np.asarray(R, dtype=float)
    p = np.asarray(pivot, dtype=float)
    xyz = np.asarray(t, dtype=float) - p + np.einsum("...ij,j->...i", Rm, p)
    return np.concatenate([xyz, xyz_angles(Rm)], axis=-1)


def object_pose(
    stage: ArrayLike, hexapod: ArrayLike, *, order: str = "stage_on_hexapod", pivot: ArrayLike = (0.0, 0.0, 0.0)
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Forward kinematics: object pose ``(R, t)`` from stage angle(s) (rad) and hexapod pose(s)."""
    _check_order(order)
    Rs = rot_z(stage)
    Rh, th = hexapod_transform(hexapod, pivot)
    if order == "stage_on_hexapod":
        return Rh @ Rs, th
    return Rs @ Rh, np.einsum("...ij,...j->...i", Rs, th)


def split_pose(
    R: ArrayLike, t: ArrayLike, stage: ArrayLike, *, order: str = "stage_on_hexapod", pivot: ArrayLike = (0.0, 0.0, 0.0)
) -> NDArray[np.float64]:
    """Inverse kinematics: hexapod pose(s) ``(..., 6)`` that, with the given stage angle(s), realise ``(R, t)``."""
    _check_order(order)
    Rm, tv = np.asarray(R, dtype=float), np.asarray(t, dtype=float)
    Rs = rot_z(stage)
    RsT = np.swapaxes(Rs, -1, -2)
    if order == "stage_on_hexapod":
        Rh, th = Rm @ RsT, tv
    else:
        Rh, th = RsT @ Rm, np.einsum("...ij,...j->...i", RsT, tv)
    return hexapod_pose_from_transform(Rh, th, pivot)
