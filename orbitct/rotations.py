"""Rotation matrices and rigid/similarity helpers shared by every part (radians inside)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def rot_x(angle: ArrayLike) -> NDArray[np.float64]:
    """Right-handed rotation(s) about +x; shape (..., 3, 3)."""
    a = np.asarray(angle, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(angle: ArrayLike) -> NDArray[np.float64]:
    """Right-handed rotation(s) about +y; shape (..., 3, 3)."""
    a = np.asarray(angle, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(angle: ArrayLike) -> NDArray[np.float64]:
    """Right-handed rotation(s) about +z; shape (..., 3, 3)."""
    a = np.asarray(angle, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def rot_xyz(rx: ArrayLike, ry: ArrayLike, rz: ArrayLike) -> NDArray[np.float64]:
    """Rotation ``R_x(rx) R_y(ry) R_z(rz)``: PI's hexapod U, V, W convention (moving axes)."""
    return rot_x(rx) @ rot_y(ry) @ rot_z(rz)


def xyz_angles(R: ArrayLike) -> NDArray[np.float64]:
    """Inverse of :func:`rot_xyz`: angles ``(rx, ry, rz)`` of ``R_x R_y R_z``; shape (..., 3)."""
    m = np.asarray(R, dtype=float)
    ry = np.arcsin(np.clip(m[..., 0, 2], -1.0, 1.0))
    rx = np.arctan2(-m[..., 1, 2], m[..., 2, 2])
    rz = np.arctan2(-m[..., 0, 1], m[..., 0, 0])
    return np.stack([rx, ry, rz], -1)


def rotvec_to_matrix(rotvec: ArrayLike) -> NDArray[np.float64]:
    """Rodrigues: rotation vector(s) (axis times angle, rad) to matrices; shape (..., 3, 3)."""
    r = np.asarray(rotvec, dtype=float)
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    k = np.zeros(r.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2] = -r[..., 2], r[..., 1]
    k[..., 1, 0], k[..., 1, 2] = r[..., 2], -r[..., 0]
    k[..., 2, 0], k[..., 2, 1] = -r[..., 1], r[..., 0]
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def matrix_to_rotvec(R: ArrayLike) -> NDArray[np.float64]:
    """Inverse of :func:`rotvec_to_matrix` for angles below pi; shape (..., 3)."""
    m = np.asarray(R, dtype=float)
    cos = np.clip((np.trace(m, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    w = np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)
    sin = np.sin(theta)
    scale = np.where(theta < 1e-8, 0.5, theta / (2.0 * np.where(sin == 0, 1.0, sin)))
    return w * scale[..., None]


def similarity_fit(
    src: ArrayLike, dst: ArrayLike, *, with_scale: bool = True
) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama); returns ``(s, R, t)``."""
    a = np.asarray(src, dtype=float).reshape(-1, 3)
    b = np.asarray(dst, dtype=float).reshape(-1, 3)
    ok = np.isfinite(a).all(1) & np.isfinite(b).all(1)
    a, b = a[ok], b[ok]
    if len(a) < 3:
        raise ValueError(f"similarity_fit needs at least 3 finite point pairs, got {len(a)}")
    ma, mb = a.mean(0), b.mean(0)
    a0, b0 = a - ma, b - mb
    cov = b0.T @ a0 / len(a)
    U, sig, Vt = np.linalg.svd(cov)
    d = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        d[2] = -1.0
    R = U @ np.diag(d) @ Vt
    s = float((sig * d).sum() / (a0**2).sum() * len(a)) if with_scale else 1.0
    t = mb - s * R @ ma
    return s, R, t
