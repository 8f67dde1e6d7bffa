"""Per-view correction model: a rigid motion of the nominal source-detector assembly, optionally with intrinsics.

A view's state is ``(R, t, k)``: the nominal view, first changed by the intrinsics ``k`` (source-detector
distance change along the detector normal, then in-plane detector shift ``du, dv``, mm), then moved rigidly
``x -> R x + t`` in the object frame (rotation about the nominal isocenter). Projecting an object point ``X``
through it equals projecting ``R^T (X - t)`` through the intrinsics-changed nominal view.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from orbitct.geometry import ViewGeometry
from orbitct.rotations import matrix_to_rotvec, rotvec_to_matrix

INTRINSICS: dict[str, int] = {"fixed": 0, "sdd": 1, "sdd+pp": 3}
_FD_STEP_MM = 1e-3


def skew(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Matrices ``[a]_x`` with ``[a]_x b = a x b``; shape ``(..., 3, 3)``."""
    z = np.zeros(a.shape[:-1])
    return np.stack(
        [
            np.stack([z, -a[..., 2], a[..., 1]], -1),
            np.stack([a[..., 2], z, -a[..., 0]], -1),
            np.stack([-a[..., 1], a[..., 0], z], -1),
        ],
        -2,
    )


@dataclass
class ViewState:
    """Current corrections of ``N`` views: rotations ``(N,3,3)``, translations ``(N,3)``, intrinsics ``(N,m)``."""

    R: NDArray[np.float64]
    t: NDArray[np.float64]
    k: NDArray[np.float64]

    @classmethod
    def identity(cls, n: int, n_intrinsics: int) -> ViewState:
        """No correction."""
        return cls(np.repeat(np.eye(3)[None], n, 0), np.zeros((n, 3)), np.zeros((n, n_intrinsics)))

    def copy(self) -> ViewState:
        """Independent copy."""
        return ViewState(self.R.copy(), self.t.copy(), self.k.copy())

    def stepped(self, delta: NDArray[np.float64]) -> ViewState:
        """State after a local step ``delta (N, 6+m)``: ``R exp([d_rot]), t + d_t, k + d_k``."""
        return ViewState(self.R @ rotvec_to_matrix(delta[:, 0:3]), self.t + delta[:, 3:6], self.k + delta[:, 6:])

    @property
    def rotvec(self) -> NDArray[np.float64]:
        """Rotation vectors ``(N, 3)`` of the corrections (rad)."""
        return matrix_to_rotvec(self.R)


class ViewModel:
    """Projection of object points through corrected nominal views, with Jacobians."""

    def __init__(self, nominal: ViewGeometry, intrinsics: str = "fixed") -> None:
        if intrinsics not in INTRINSICS:
            raise ValueError(f"intrinsics must be one of {sorted(INTRINSICS)}, got {intrinsics!r}")
        self.nominal = nominal
        self.intrinsics = intrinsics
        self.n_intrinsics = INTRINSICS[intrinsics]
        self.n_params = 6 + self.n_intrinsics
        self._normal = nominal.normal
        self._uhat = nominal.u / np.linalg.norm(nominal.u, axis=1, keepdims=True)
        self._vhat = nominal.v / np.linalg.norm(nominal.v, axis=1, keepdims=True)

    def identity(self) -> ViewState:
        """State with no correction."""
        return ViewState.identity(self.nominal.n_views, self.n_intrinsics)

    def base(self, k: NDArray[np.float64]) -> ViewGeometry:
        """Nominal views with the intrinsics ``k`` applied (before the rigid motion)."""
        if self.n_intrinsics == 0:
            return self.nominal
        vec = self.nominal.vectors.copy()
        vec[:, 3:6] += k[:, 0:1] * self._normal
        if self.n_intrinsics == 3:
            vec[:, 3:6] += k[:, 1:2] * self._uhat + k[:, 2:3] * self._vhat
        return self.nominal.with_vectors(vec)

    def geometry(self, state: ViewState) -> ViewGeometry:
        """Corrected views."""
        return self.base(state.k).transformed(state.R, state.t)

    @staticmethod
    def _project(P: NDArray[np.float64], Y: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        h = Y @ np.swapaxes(P[:, :, :3], 1, 2) + P[:, None, :, 3]
        return h[..., :2] / h[..., 2:3], h

    def project(self, state: ViewState, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
        """Pixels ``(N, K, 2)`` of points ``(K, 3)``."""
        Y = (xyz[None] - state.t[:, None]) @ state.R
        return self._project(self.base(state.k).matrices, Y)[0]

    def project_jac(
        self, state: ViewState, xyz: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Pixels ``(N,K,2)``, Jacobians w.r.t. the view step ``(N,K,2,6+m)`` and the points ``(N,K,2,3)``."""
        P = self.base(state.k).matrices
        Rt = np.swapaxes(state.R, 1, 2)
        Y = (xyz[None] - state.t[:, None]) @ state.R
        uv, h = self._project(P, Y)
        w = h[..., 2]
        M = P[:, :, :3]
        JY = (M[:, None, 0:2, :] - uv[..., :, None] * M[:, None, 2:3, :]) / w[..., None, None]  # (N,K,2,3)
        Jp = JY @ Rt[:, None]
        Jv = np.empty(uv.shape + (self.n_params,))
        # JY [Y]_x, row by row: r [Y]_x = r x Y
        Yb = Y[..., None, :]
        Jv[..., 0] = JY[..., 1] * Yb[..., 2] - JY[..., 2] * Yb[..., 1]
        Jv[..., 1] = JY[..., 2] * Yb[..., 0] - JY[..., 0] * Yb[..., 2]
        Jv[..., 2] = JY[..., 0] * Yb[..., 1] - JY[..., 1] * Yb[..., 0]
        Jv[..., 3:6] = -Jp
        for j in range(self.n_intrinsics):
            k2 = state.k.copy()
            k2[:, j] += _FD_STEP_MM
            uv2 = self._project(self.base(k2).matrices, Y)[0]
            Jv[..., 6 + j] = (uv2 - uv) / _FD_STEP_MM
        return uv, Jv, Jp


def all_finite(a: NDArray[Any]) -> NDArray[np.bool_]:
    """Where every value along the last axis is finite: a BB seen (``uv``), a ray or point defined."""
    return np.logical_and.reduce(np.isfinite(a), axis=-1)
