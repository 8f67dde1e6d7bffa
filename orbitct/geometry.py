"""Per-view cone-beam geometry: the one place that speaks ``geometry.md``.

A :class:`ViewGeometry` is immutable. It holds ``(N, 12)`` vectors ``S, D, u, v``
(ASTRA ``cone_vec`` order, object frame, millimetres) and the :class:`Panel`
they refer to; every operation returns a new object. Beside it, a
:class:`VolumeGrid` samples the object frame with voxels (as tomosipo pairs a
volume geometry with the projection geometry).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbitct.rotations import rot_x, rot_z

__all__ = ["GeometryError", "Panel", "ViewGeometry", "VolumeGrid", "ideal_bench_pose"]


class GeometryError(ValueError):
    """Geometry input of the wrong shape or meaning."""


@dataclass(frozen=True)
class Panel:
    """The pixel grid of a flat panel: frame shape and pixel pitch (mm)."""

    rows: int
    cols: int
    pitch_col: float
    pitch_row: float

    def __post_init__(self) -> None:
        if int(self.rows) < 1 or int(self.cols) < 1:
            raise GeometryError(f"panel rows and cols must be >= 1, got rows={self.rows}, cols={self.cols}")
        if not (self.pitch_col > 0 and self.pitch_row > 0):
            raise GeometryError(
                f"panel pitches must be > 0 mm, got pitch_col={self.pitch_col}, pitch_row={self.pitch_row}"
            )
        object.__setattr__(self, "rows", int(self.rows))
        object.__setattr__(self, "cols", int(self.cols))
        object.__setattr__(self, "pitch_col", float(self.pitch_col))
        object.__setattr__(self, "pitch_row", float(self.pitch_row))

    @property
    def shape(self) -> tuple[int, int]:
        """Frame shape ``(rows, cols)``."""
        return (self.rows, self.cols)

    @property
    def pitch_mm(self) -> tuple[float, float]:
        """``(column pitch, row pitch)`` as stored in scan files."""
        return (self.pitch_col, self.pitch_row)

    @property
    def mean_pitch_mm(self) -> float:
        """The geometric mean of the two pitches: one pixel's size for isotropic things (blur, a BB's diameter)."""
        return math.sqrt(self.pitch_col * self.pitch_row)

    @property
    def center(self) -> tuple[float, float]:
        """Pixel coordinate ``(col, row)`` of the detector centre ``D``."""
        return ((self.cols - 1) / 2.0, (self.rows - 1) / 2.0)

    def binned(self, factor: int) -> Panel:
        """Panel after ``factor x factor`` binning."""
        return Panel(self.rows // factor, self.cols // factor, self.pitch_col * factor, self.pitch_row * factor)


def _as_views(a: ArrayLike, width: int, name: str) -> NDArray[np.float64]:
    arr = np.asarray(a, dtype=float)
    if arr.ndim == 1 and arr.shape[0] == width:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != width:
        raise GeometryError(f"{name}: expected shape (N, {width}), got {arr.shape}")
    return arr


def _per_view(a: ArrayLike, n: int, name: str, tail: tuple[int, ...] = ()) -> NDArray[np.float64]:
    arr = np.asarray(a, dtype=float)
    try:
        return np.broadcast_to(arr, (n,) + tail).copy()
    except ValueError:
        raise GeometryError(f"{name}: expected a scalar or shape {(n,) + tail}, got {arr.shape}") from None


def ideal_bench_pose(theta: ArrayLike, phi: ArrayLike) -> NDArray[np.float64]:
    """Object rotation(s) ``R = R_x(phi) R_z(-theta)`` that realise a nominal view on the bench."""
    return rot_x(phi) @ rot_z(-np.asarray(theta, dtype=float))


class ViewGeometry:
    """Immutable per-view geometry: ``(N, 12)`` vectors ``S, D, u, v`` and a panel."""

    __slots__ = ("_matrices", "_panel", "_vectors")

    def __init__(self, vectors: ArrayLike, panel: Panel) -> None:
        if not isinstance(panel, Panel):
            raise GeometryError(f"panel: expected a Panel, got {type(panel).__name__}")
        v = _as_views(vectors, 12, "vectors").copy()
        v.setflags(write=False)
        self._vectors = v
        self._panel = panel
        self._matrices: NDArray[np.float64] | None = None

    # ----------------------------------------------------------------- basics
    @property
    def vectors(self) -> NDArray[np.float64]:
        """Read-only ``(N, 12)`` array ``S, D, u, v``."""
        return self._vectors

    @property
    def panel(self) -> Panel:
        """The panel (pixel grid) these views refer to."""
        return self._panel

    @property
    def n_views(self) -> int:
        """Number of views."""
        return self._vectors.shape[0]

    def __len__(self) -> int:
        return self.n_views

    @property
    def S(self) -> NDArray[np.float64]:
        """Source positions ``(N, 3)``."""
        return self._vectors[:, 0:3]

    @property
    def D(self) -> NDArray[np.float64]:
        """Detector centres ``(N, 3)``."""
        return self._vectors[:, 3:6]

    @property
    def u(self) -> NDArray[np.float64]:
        """Column step vectors ``(N, 3)`` (length = column pitch)."""
        return self._vectors[:, 6:9]

    @property
    def v(self) -> NDArray[np.float64]:
        """Row step vectors ``(N, 3)`` (length = row pitch)."""
        return self._vectors[:, 9:12]

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Views whose 12 numbers are all finite."""
        return np.asarray(np.isfinite(self._vectors).all(axis=1))

    @property
    def normal(self) -> NDArray[np.float64]:
        """Unit detector normals pointing from the source towards the detector ``(N, 3)``."""
        n = np.cross(self.u, self.v)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        sign = np.sign(np.einsum("ij,ij->i", n, self.D - self.S))
        return n * sign[:, None]

    @property
    def sdd(self) -> NDArray[np.float64]:
        """Source-to-detector-plane distance per view (mm)."""
        return np.einsum("ij,ij->i", self.normal, self.D - self.S)

    def sod(self, isocenter: ArrayLike = (0.0, 0.0, 0.0)) -> NDArray[np.float64]:
        """Source-to-point distance per view (mm), by default to the object origin."""
        return np.linalg.norm(self.S - np.asarray(isocenter, dtype=float), axis=1)

    def projected_size_px(self, size_mm: float) -> NDArray[np.float64]:
        """Per view, how many pixels an object ``size_mm`` across at the isocenter spans on the panel (the
        magnification SDD / SOD over the panel's mean pitch; NaN where a view has no geometry)."""
        panel = self._panel
        return float(size_mm) * self.sdd / self.sod() / float(np.sqrt(panel.pitch_col * panel.pitch_row))

    # ----------------------------------------------------------- matrices
    @property
    def matrices(self) -> NDArray[np.float64]:
        """``(N, 3, 4)`` projection matrices, normalised so ``w`` is depth in mm."""
        if self._matrices is None:
            m = _vectors_to_matrices(self._vectors, self._panel)
            m.setflags(write=False)
            self._matrices = m
        return self._matrices

    @classmethod
    def from_matrices(cls, matrices: ArrayLike, panel: Panel) -> ViewGeometry:
        """Views from ``(N, 3, 4)`` projection matrices (any positive or negative scale)."""
        p = np.asarray(matrices, dtype=float)
        if p.ndim == 2 and p.shape == (3, 4):
            p = p[None]
        if p.ndim != 3 or p.shape[1:] != (3, 4):
            raise GeometryError(f"matrices: expected shape (N, 3, 4), got {p.shape}")
        return cls(_matrices_to_vectors(p, panel), panel)

    # -------------------------------------------------------- constructors
    @classmethod
    def from_carm(
        cls,
        theta: ArrayLike,
        phi: ArrayLike,
        sad: ArrayLike,
        sdd: ArrayLike,
        panel: Panel,
        *,
        du: ArrayLike = 0.0,
        dv: ArrayLike = 0.0,
        eta: ArrayLike = 0.0,
        shift: ArrayLike = (0.0, 0.0, 0.0),
    ) -> ViewGeometry:
        """Views from C-arm style parameters (radians, mm), broadcast over views."""
        theta_a = np.atleast_1d(np.asarray(theta, dtype=float))
        n = int(np.broadcast_shapes(theta_a.shape, np.atleast_1d(np.asarray(phi, dtype=float)).shape)[0])
        th = _per_view(theta_a, n, "theta")
        ph = _per_view(phi, n, "phi")
        sad_a, sdd_a = _per_view(sad, n, "sad"), _per_view(sdd, n, "sdd")
        du_a, dv_a, eta_a = _per_view(du, n, "du"), _per_view(dv, n, "dv"), _per_view(eta, n, "eta")
        t = _per_view(shift, n, "shift", (3,))
        if np.any(sdd_a <= sad_a):
            raise GeometryError("sdd must exceed sad for every view (detector beyond the isocenter)")
        d = np.stack([np.sin(th) * np.cos(ph), -np.cos(th) * np.cos(ph), np.sin(ph)], -1)
        uh = np.stack([np.cos(th), np.sin(th), np.zeros(n)], -1)
        vh = np.cross(uh, d)
        ce, se = np.cos(eta_a)[:, None], np.sin(eta_a)[:, None]
        uh2 = ce * uh + se * vh
        vh2 = -se * uh + ce * vh
        S = t + sad_a[:, None] * d
        D = t - (sdd_a - sad_a)[:, None] * d + du_a[:, None] * uh2 + dv_a[:, None] * vh2
        vec = np.concatenate([S, D, panel.pitch_col * uh2, panel.pitch_row * vh2], axis=1)
        return cls(vec, panel)

    @classmethod
    def from_object_poses(cls, lab_view: ViewGeometry, R: ArrayLike, t: ArrayLike) -> ViewGeometry:
        """Bench views: fixed lab source/detector (one view) seen from objects at poses ``x_lab = R x + t``."""
        if lab_view.n_views != 1:
            raise GeometryError(f"lab_view: expected exactly 1 view, got {lab_view.n_views}")
        Rm = np.asarray(R, dtype=float)
        if Rm.ndim == 2:
            Rm = Rm[None]
        if Rm.ndim != 3 or Rm.shape[1:] != (3, 3):
            raise GeometryError(f"R: expected shape (N, 3, 3), got {Rm.shape}")
        tv = _per_view(t, Rm.shape[0], "t", (3,))
        Rt = np.swapaxes(Rm, 1, 2)
        S, D, u, v = (lab_view.vectors[0, 3 * k : 3 * k + 3] for k in range(4))
        out = np.concatenate(
            [
                np.einsum("nij,nj->ni", Rt, S - tv),
                np.einsum("nij,nj->ni", Rt, D - tv),
                np.einsum("nij,j->ni", Rt, u),
                np.einsum("nij,j->ni", Rt, v),
            ],
            axis=1,
        )
        return cls(out, lab_view.panel)

    @classmethod
    def empty_like(cls, n_views: int, panel: Panel) -> ViewGeometry:
        """``n_views`` views that are all NaN (frames that are not projections)."""
        return cls(np.full((n_views, 12), np.nan), panel)

    # ----------------------------------------------------------- operations
    def __getitem__(self, index: Any) -> ViewGeometry:
        idx = np.arange(self.n_views)[index]
        return ViewGeometry(self._vectors[np.atleast_1d(idx)], self._panel)

    def with_vectors(self, vectors: ArrayLike) -> ViewGeometry:
        """Same panel, new vectors."""
        return ViewGeometry(vectors, self._panel)

    def with_panel(self, panel: Panel) -> ViewGeometry:
        """Same views re-expressed for another sampling of the same panel plane."""
        vec = self._vectors.copy()
        vec[:, 6:9] *= panel.pitch_col / self._panel.pitch_col
        vec[:, 9:12] *= panel.pitch_row / self._panel.pitch_row
        return ViewGeometry(vec, panel)

    def concatenate(self, *others: ViewGeometry) -> ViewGeometry:
        """Views of ``self`` followed by those of ``others`` (same panel required)."""
        for o in others:
            if o.panel != self._panel:
                raise GeometryError(f"cannot concatenate geometries with panels {self._panel} and {o.panel}")
        return ViewGeometry(np.concatenate([self._vectors] + [o.vectors for o in others]), self._panel)

    def transformed(self, R: ArrayLike, t: ArrayLike = (0.0, 0.0, 0.0)) -> ViewGeometry:
        """Apply rigid transform(s) ``x -> R x + t`` (one, or one per view) to every view."""
        Rm = np.asarray(R, dtype=float)
        if Rm.shape == (3, 3):
            Rm = np.broadcast_to(Rm, (self.n_views, 3, 3))
        if Rm.shape != (self.n_views, 3, 3):
            raise GeometryError(f"R: expected shape (3, 3) or ({self.n_views}, 3, 3), got {Rm.shape}")
        tv = _per_view(t, self.n_views, "t", (3,))
        parts = [np.einsum("nij,nj->ni", Rm, self._vectors[:, 3 * k : 3 * k + 3]) for k in range(4)]
        parts[0] = parts[0] + tv
        parts[1] = parts[1] + tv
        return ViewGeometry(np.concatenate(parts, axis=1), self._panel)

    def scaled(self, s: float) -> ViewGeometry:
        """Scale positions about the origin by ``s`` (pixel pitches unchanged)."""
        vec = self._vectors.copy()
        vec[:, 0:6] *= s
        return ViewGeometry(vec, self._panel)

    # ------------------------------------------------------------- project
    def project(self, points: ArrayLike) -> NDArray[np.float64]:
        """Pixel coordinates ``(col, row)`` of points: ``(K, 3)`` or ``(N, K, 3)`` -> ``(N, K, 2)``."""
        uv, _ = self.project_with_depth(points)
        return uv

    def project_with_depth(self, points: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixel coordinates ``(N, K, 2)`` and depths ``(N, K)`` (mm along the detector normal)."""
        p = np.asarray(points, dtype=float)
        if p.ndim == 1 and p.shape[0] == 3:
            p = p[None]
        if p.shape[-1] != 3 or p.ndim not in (2, 3):
            raise GeometryError(f"points: expected shape (K, 3) or (N, K, 3), got {p.shape}")
        if p.ndim == 3 and p.shape[0] != self.n_views:
            raise GeometryError(f"points: expected {self.n_views} views in (N, K, 3), got {p.shape}")
        P = self.matrices
        h = np.matmul(p, np.swapaxes(P[:, :, :3], 1, 2)) + P[:, None, :, 3]  # (N, K, 3)
        w = h[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return h[..., :2] / w[..., None], w

    def pixel_to_point(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Object-frame points on the detector for pixel coordinates ``(N, K, 2)`` -> ``(N, K, 3)``."""
        px = np.asarray(pixels, dtype=float)
        if px.ndim == 2:
            px = np.broadcast_to(px, (self.n_views,) + px.shape)
        if px.ndim != 3 or px.shape[0] != self.n_views or px.shape[2] != 2:
            raise GeometryError(f"pixels: expected shape (K, 2) or ({self.n_views}, K, 2), got {px.shape}")
        c0, r0 = self._panel.center
        dc = px[..., 0] - c0
        dr = px[..., 1] - r0
        return self.D[:, None, :] + dc[..., None] * self.u[:, None, :] + dr[..., None] * self.v[:, None, :]

    def backproject(self, pixels: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Rays through pixels ``(N, K, 2)``: origins ``(N, 1, 3)`` (the sources) and unit directions ``(N, K, 3)``."""
        pts = self.pixel_to_point(pixels)
        d = pts - self.S[:, None, :]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return self.S[:, None, :], d

    # ------------------------------------------------------------ compare
    def allclose(self, other: ViewGeometry, atol_mm: float = 1e-6, rtol: float = 1e-9) -> bool:
        """Same panel and vectors equal within tolerance (NaN equals NaN)."""
        if not isinstance(other, ViewGeometry) or other.panel != self._panel:
            return False
        if other.n_views != self.n_views:
            return False
        return bool(np.allclose(self._vectors, other.vectors, atol=atol_mm, rtol=rtol, equal_nan=True))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ViewGeometry) and self.allclose(other, atol_mm=1e-9, rtol=1e-9)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        d = self._panel
        ok = self.valid
        if ok.any():
            sod = np.nanmedian(self.sod()[ok])
            sdd = np.nanmedian(self.sdd[ok])
            extra = f", sod~{sod:.1f} mm, sdd~{sdd:.1f} mm"
        else:
            extra = ""
        nan = f", {int((~ok).sum())} NaN" if (~ok).any() else ""
        return (
            f"ViewGeometry(n_views={self.n_views}{nan}, panel={d.rows}x{d.cols} px @ "
            f"{d.pitch_col:g}x{d.pitch_row:g} mm{extra})"
        )


def _center_matrix(det: Panel) -> NDArray[np.float64]:
    c0, r0 = det.center
    return np.array([[1.0, 0.0, c0], [0.0, 1.0, r0], [0.0, 0.0, 1.0]])


def _vectors_to_matrices(vec: NDArray[np.float64], det: Panel) -> NDArray[np.float64]:
    n = vec.shape[0]
    out = np.full((n, 3, 4), np.nan)
    ok = np.isfinite(vec).all(axis=1)
    if not ok.any():
        return out
    S, D, u, v = (vec[ok, 3 * k : 3 * k + 3] for k in range(4))
    A = np.stack([u, v, D - S], axis=-1)
    Ainv = np.linalg.inv(A)
    P0 = np.concatenate([Ainv, -np.einsum("nij,nj->ni", Ainv, S)[..., None]], axis=-1)
    P = _center_matrix(det) @ P0
    P /= np.linalg.norm(P[:, 2, :3], axis=1)[:, None, None]
    out[ok] = P
    return out


def _matrices_to_vectors(P: NDArray[np.float64], det: Panel) -> NDArray[np.float64]:
    n = P.shape[0]
    out = np.full((n, 12), np.nan)
    ok = np.isfinite(P).all(axis=(1, 2))
    if not ok.any():
        return out
    P0 = np.linalg.inv(_center_matrix(det)) @ P[ok]
    M = P0[:, :, :3]
    try:
        A = np.linalg.inv(M)
    except np.linalg.LinAlgError:
        raise GeometryError("matrices: the left 3x3 block of a projection matrix is singular") from None
    S = -np.einsum("nij,nj->ni", A, P0[:, :, 3])
    u, v, dz = A[:, :, 0], A[:, :, 1], A[:, :, 2]
    scale = np.sqrt(np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1) / (det.pitch_col * det.pitch_row))
    # the overall sign of P is free: pick the right-handed frame det[u, v, D - S] > 0 (as every from_carm view)
    sign = np.sign(np.linalg.det(A))
    s = (sign / scale)[:, None]
    u, v, dz = u * s, v * s, dz * s
    out[ok] = np.concatenate([S, S + dz, u, v], axis=1)
    return out


@dataclass(frozen=True)
class VolumeGrid:
    """Regular grid: ``shape`` (nz, ny, nx), ``voxel_mm`` and ``origin_mm`` (x, y, z; centre of voxel [0,0,0])."""

    shape: tuple[int, int, int]
    voxel_mm: tuple[float, float, float]
    origin_mm: tuple[float, float, float]

    def __post_init__(self) -> None:
        shape = tuple(int(s) for s in self.shape)
        vox = tuple(float(v) for v in np.broadcast_to(np.asarray(self.voxel_mm, dtype=float), (3,)))
        org = tuple(float(v) for v in np.asarray(self.origin_mm, dtype=float).ravel())
        if len(shape) != 3 or min(shape) < 1:
            raise GeometryError(f"grid shape must be 3 positive integers (nz, ny, nx), got {self.shape}")
        if min(vox) <= 0:
            raise GeometryError(f"voxel_mm must be > 0, got {self.voxel_mm}")
        if len(org) != 3 or not np.all(np.isfinite(org)):
            raise GeometryError(f"origin_mm must be 3 finite numbers (x, y, z), got {self.origin_mm}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "voxel_mm", vox)
        object.__setattr__(self, "origin_mm", org)

    @classmethod
    def centered(
        cls,
        shape: tuple[int, int, int],
        voxel_mm: float | tuple[float, float, float],
        center_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> VolumeGrid:
        """Grid of ``shape`` whose centre sits at ``center_mm`` (default the isocenter)."""
        vox = np.broadcast_to(np.asarray(voxel_mm, dtype=float), (3,))
        n_xyz = np.array(shape[::-1], dtype=float)
        origin = np.asarray(center_mm, dtype=float) - (n_xyz - 1) / 2 * vox
        return cls(cast(tuple[int, int, int], tuple(shape)), tuple(vox), tuple(origin))  # checked there

    @property
    def size(self) -> int:
        """Number of voxels."""
        return int(np.prod(self.shape))

    @property
    def nbytes(self) -> int:
        """Bytes of one float32 volume."""
        return 4 * self.size

    @property
    def extent_mm(self) -> NDArray[np.float64]:
        """``(3, 2)`` low/high edges of the grid along x, y, z."""
        vox = np.asarray(self.voxel_mm)
        lo = np.asarray(self.origin_mm) - vox / 2
        hi = lo + vox * np.array(self.shape[::-1])
        return np.stack([lo, hi], axis=1)

    def coords_mm(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """1-D voxel-centre coordinates ``(z, y, x)``."""
        return tuple(  # type: ignore[return-value]
            self.origin_mm[a] + self.voxel_mm[a] * np.arange(self.shape[2 - a]) for a in (2, 1, 0)
        )

    def to_json(self) -> dict[str, list[float] | list[int]]:
        """Plain description for attributes and logs."""
        return {"shape": list(self.shape), "voxel_mm": list(self.voxel_mm), "origin_mm": list(self.origin_mm)}
