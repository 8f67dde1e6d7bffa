"""Where BBs can be taped: an object's outer surface, addressed by an angle about the object frame's z axis and a
height, as the BB planner searches it; a person finds a place on the object by its polar angle
(:func:`polar_angle`) and height.

``EllipticCylinder`` and ``Ellipsoid`` are surfaces given by parameters (:func:`shape_from_text`; the experiments'
objects are elliptic cylinders), addressed by the ellipse's own
angle parameter (evenly spread round it), which differs from the polar angle where the semi-axes differ (up to 8
degrees on experiment C's torso); ``Outline`` is the outermost surface of a real object, from a mask of a prior
volume or from points on a surface mesh, as a radius per polar angle and height (star-shaped about the z axis: what
a BB taped on the outside can reach), addressed by the polar angle itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray


class TapeSurface(Protocol):
    """What the planner needs of a surface, addressed by an angle (rad) about z and a height (mm)."""

    z_min_mm: float
    z_max_mm: float

    def points(
        self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64], diameter_mm: float
    ) -> NDArray[np.float64]:
        """BB centres on the surface (a BB's radius outside it) at these addresses (angle, height)."""
        ...

    def covers(self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether the object has surface at these addresses (angle, height)."""
        ...

    def describe(self) -> dict[str, Any]:
        """The surface in a few JSON-ready numbers."""
        ...


@dataclass(frozen=True)
class EllipticCylinder:
    """The side of an elliptic cylinder about the z axis (semi-axes ``a_mm`` along x and ``b_mm`` along y), between
    heights ``z_min_mm`` and ``z_max_mm``; the address angle t is the ellipse's parameter, at ``(a cos t, b sin t)``."""

    a_mm: float
    b_mm: float
    z_min_mm: float
    z_max_mm: float

    def points(
        self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64], diameter_mm: float
    ) -> NDArray[np.float64]:
        """BB centres on the surface (a BB's radius outside it) at these parameter angles and heights."""
        p = np.stack([self.a_mm * np.cos(angle_rad), self.b_mm * np.sin(angle_rad), np.zeros_like(angle_rad)], -1)
        normal = np.stack([np.cos(angle_rad) / self.a_mm, np.sin(angle_rad) / self.b_mm, np.zeros_like(angle_rad)], -1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        return p + 0.5 * diameter_mm * normal + np.stack([0 * z_mm, 0 * z_mm, z_mm], -1)

    def covers(self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Everywhere between the two heights."""
        return (np.asarray(z_mm) >= self.z_min_mm) & (np.asarray(z_mm) <= self.z_max_mm)

    def describe(self) -> dict[str, Any]:
        """Kind and parameters."""
        return {"kind": "elliptic cylinder", **vars(self)}


@dataclass(frozen=True)
class Ellipsoid:
    """An ellipsoid about the isocentre (semi-axes ``a_mm`` along x, ``b_mm`` along y, ``c_mm`` along z), where BBs
    go between heights ``z_min_mm`` and ``z_max_mm``; the address angle t is the parameter of the ellipse cut at the
    height, at ``s (a cos t, b sin t)`` with ``s = sqrt(1 - z^2 / c^2)``."""

    a_mm: float
    b_mm: float
    c_mm: float
    z_min_mm: float
    z_max_mm: float

    def points(
        self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64], diameter_mm: float
    ) -> NDArray[np.float64]:
        """BB centres a BB's radius outside the surface along its normal."""
        ang, z = np.asarray(angle_rad, dtype=float), np.asarray(z_mm, dtype=float)
        shrink = np.sqrt(np.clip(1.0 - (z / self.c_mm) ** 2, 0.0, None))
        p = np.stack([self.a_mm * shrink * np.cos(ang), self.b_mm * shrink * np.sin(ang), z], -1)
        normal = p / np.array([self.a_mm, self.b_mm, self.c_mm]) ** 2
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        return p + 0.5 * diameter_mm * normal

    def covers(self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Everywhere between the two heights."""
        return (np.asarray(z_mm) >= self.z_min_mm) & (np.asarray(z_mm) <= self.z_max_mm)

    def describe(self) -> dict[str, Any]:
        """Kind and parameters."""
        return {"kind": "ellipsoid", **vars(self)}


def shape_from_text(text: str) -> EllipticCylinder | Ellipsoid:
    """A surface by parameters (mm): ``cylinder:R,ZMIN:ZMAX``, ``cylinder:A,B,ZMIN:ZMAX`` (semi-axes along x and
    y) or ``ellipsoid:A,B,C`` (semi-axes along x, y, z, about the isocentre; BBs within 0.9 C of its middle, or
    ``ellipsoid:A,B,C,ZMIN:ZMAX``). ValueError naming what is wrong."""
    kind, _, rest = text.partition(":")
    usage = {
        "cylinder": "cylinder:R,ZMIN:ZMAX or cylinder:A,B,ZMIN:ZMAX",
        "ellipsoid": "ellipsoid:A,B,C or ellipsoid:A,B,C,ZMIN:ZMAX",
    }
    if kind not in usage:
        raise ValueError(f"shape {text!r}: expected {usage['cylinder']} or {usage['ellipsoid']} (mm)")
    parts = rest.split(",")
    band = parts.pop() if parts and ":" in parts[-1] else None
    try:
        axes = [float(v) for v in parts]
        z = [float(v) for v in band.split(":")] if band is not None else None
    except ValueError:
        raise ValueError(f"shape {text!r}: expected {usage[kind]} (numbers, mm)") from None
    if not all(np.isfinite(v) and 0.0 < v <= 1000.0 for v in axes):
        raise ValueError(f"shape {text!r}: semi-axes must be in (0, 1000] mm")
    if z is not None and not (len(z) == 2 and all(np.isfinite(z)) and z[0] < z[1]):
        raise ValueError(f"shape {text!r}: heights ZMIN:ZMAX must be two numbers, the lower first")
    if kind == "cylinder" and len(axes) in (1, 2) and z is not None:
        return EllipticCylinder(axes[0], axes[-1], z[0], z[1])
    if kind == "ellipsoid" and len(axes) == 3:
        c = axes[2]
        lo, hi = z if z is not None else (-0.9 * c, 0.9 * c)
        if lo < -c or hi > c:
            raise ValueError(f"shape {text!r}: the heights must lie within the ellipsoid's -{c:g} to {c:g} mm")
        return Ellipsoid(axes[0], axes[1], c, lo, hi)
    raise ValueError(f"shape {text!r}: expected {usage[kind]} (mm)")


@dataclass(frozen=True)
class Outline:
    """An object's outer surface as its radius (mm, NaN where there is none) on a grid of polar angles (``n_angles``
    evenly over the turn, from +x counterclockwise) and heights ``z_mm``; between grid points it is interpolated."""

    z_mm: NDArray[np.float64]  # (Z,) increasing
    radius_mm: NDArray[np.float64]  # (Z, A)
    source: str = ""

    @property
    def z_min_mm(self) -> float:
        return float(self.z_mm[np.isfinite(self.radius_mm).any(1)].min())

    @property
    def z_max_mm(self) -> float:
        return float(self.z_mm[np.isfinite(self.radius_mm).any(1)].max())

    def _radius(self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Bilinear in (height, angle), periodic in angle; NaN outside the heights or where a corner has none."""
        n_a = self.radius_mm.shape[1]
        fa = (np.asarray(angle_rad) % (2 * np.pi)) / (2 * np.pi) * n_a
        a0 = np.floor(fa).astype(int) % n_a
        a1 = (a0 + 1) % n_a
        wa = fa - np.floor(fa)
        z = np.asarray(z_mm, dtype=float)
        inside = (z >= self.z_mm[0]) & (z <= self.z_mm[-1])
        k0 = np.clip(np.searchsorted(self.z_mm, z, side="right") - 1, 0, self.z_mm.size - 2)
        wz = np.clip((z - self.z_mm[k0]) / np.diff(self.z_mm)[k0], 0.0, 1.0)
        r = self.radius_mm
        value = (1 - wz) * ((1 - wa) * r[k0, a0] + wa * r[k0, a1]) + wz * (
            (1 - wa) * r[k0 + 1, a0] + wa * r[k0 + 1, a1]
        )
        return np.where(inside, value, np.nan)

    def covers(self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Where the interpolated radius exists."""
        return np.isfinite(self._radius(angle_rad, z_mm))

    def points(
        self, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64], diameter_mm: float
    ) -> NDArray[np.float64]:
        """BB centres a BB's radius outside the surface along its normal (from the radius' slopes)."""
        ang, z = np.asarray(angle_rad, dtype=float), np.asarray(z_mm, dtype=float)
        r = self._radius(ang, z)
        da, dz = 1e-3, 0.25
        dr_da = (self._radius(ang + da, z) - self._radius(ang - da, z)) / (2 * da)
        dr_dz = (self._radius(ang, z + dz) - self._radius(ang, z - dz)) / (2 * dz)
        dr_da, dr_dz = np.nan_to_num(dr_da), np.nan_to_num(dr_dz)
        radial = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)
        tangential = np.stack([-np.sin(ang), np.cos(ang), np.zeros_like(ang)], -1)
        up = np.stack([np.zeros_like(ang), np.zeros_like(ang), np.ones_like(ang)], -1)
        normal = radial - (dr_da / np.maximum(r, 1e-6))[..., None] * tangential - dr_dz[..., None] * up
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        return r[..., None] * radial + z[..., None] * up + 0.5 * diameter_mm * normal

    def describe(self) -> dict[str, Any]:
        """Kind, source, heights and the range of radii."""
        r = self.radius_mm[np.isfinite(self.radius_mm)]
        return {
            "kind": "outline",
            "source": self.source,
            "z_min_mm": self.z_min_mm,
            "z_max_mm": self.z_max_mm,
            "radius_mm": [float(r.min()), float(r.max())] if r.size else None,
            "angles": int(self.radius_mm.shape[1]),
        }

    @classmethod
    def from_points(
        cls, xyz: NDArray[np.float64], *, n_angles: int = 180, z_step_mm: float = 2.0, source: str = ""
    ) -> Outline:
        """The outermost of many points on an object's surface (e.g. sampled from a mesh), per angle and height."""
        xyz = np.asarray(xyz, dtype=float)
        if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) < 100:
            raise ValueError(f"an outline needs 100 or more surface points (x, y, z), got an array of {xyz.shape}")
        z_edges = np.arange(xyz[:, 2].min(), xyz[:, 2].max() + z_step_mm, z_step_mm)
        if z_edges.size < 3:
            raise ValueError(f"the object spans {np.ptp(xyz[:, 2]):.1f} mm in z: too flat to tape BBs around")
        k = np.clip(np.digitize(xyz[:, 2], z_edges) - 1, 0, z_edges.size - 2)
        ang = np.arctan2(xyz[:, 1], xyz[:, 0]) % (2 * np.pi)
        j = np.minimum((ang / (2 * np.pi) * n_angles).astype(int), n_angles - 1)
        rho = np.hypot(xyz[:, 0], xyz[:, 1])
        radius = np.full((z_edges.size - 1, n_angles), -np.inf)
        np.maximum.at(radius, (k, j), rho)
        radius[~np.isfinite(radius)] = np.nan
        return cls(0.5 * (z_edges[1:] + z_edges[:-1]), _fill_angles(radius), source)

    @classmethod
    def from_mask(
        cls,
        mask: NDArray[np.bool_],
        voxel_mm: tuple[float, float, float],
        origin_mm: tuple[float, float, float],
        *,
        n_angles: int = 180,
        source: str = "",
    ) -> Outline:
        """The outer surface of the voxels set in ``mask`` (nz, ny, nx) of a prior volume on its grid (voxel sizes
        and the first voxel's centre, x y z, in the object frame): per slice and angle, the farthest set voxel."""
        mask = np.asarray(mask, dtype=bool)
        if mask.ndim != 3 or not mask.any():
            raise ValueError("the prior volume has no voxel above the threshold: no object to tape BBs on")
        vx, vy, vz = voxel_mm
        x0, y0, z0 = origin_mm
        slices = np.flatnonzero(mask.any((1, 2)))
        step = max(1, int(round(2.0 / vz)))  # about every 2 mm in z
        rows = slices[::step]
        ang = (np.arange(n_angles) + 0.5) / n_angles * 2 * np.pi
        ny, nx = mask.shape[1:]
        r_max = float(np.hypot(max(abs(x0), abs(x0 + (nx - 1) * vx)), max(abs(y0), abs(y0 + (ny - 1) * vy))))
        ds = 0.5 * min(vx, vy)
        s = np.arange(0.0, r_max + ds, ds)
        ix = np.rint((s[None, :] * np.cos(ang)[:, None] - x0) / vx).astype(int)  # (A, S)
        iy = np.rint((s[None, :] * np.sin(ang)[:, None] - y0) / vy).astype(int)
        on = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        radius = np.full((rows.size, n_angles), np.nan)
        for n, k in enumerate(rows):
            hit = np.zeros(on.shape, bool)
            hit[on] = mask[k, iy[on], ix[on]]
            last = np.where(hit.any(1), s.size - 1 - np.argmax(hit[:, ::-1], axis=1), -1)
            radius[n] = np.where(last >= 0, s[np.maximum(last, 0)] + 0.5 * min(vx, vy), np.nan)
        return cls((z0 + rows * vz).astype(np.float64), _fill_angles(radius), source)


def polar_angle(surface: TapeSurface, angle_rad: NDArray[np.float64], z_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """The polar angle (rad, counterclockwise from +x, in [0, 2 pi)) of the surface at these addresses: where a person
    finds the place on the object."""
    p = surface.points(np.asarray(angle_rad, dtype=float), np.asarray(z_mm, dtype=float), 0.0)
    return np.arctan2(p[..., 1], p[..., 0]) % (2 * np.pi)


def address_angle(surface: TapeSurface, polar_rad: NDArray[np.float64], z_mm: float) -> NDArray[np.float64]:
    """The address angles of the surface at polar angles and one height (the inverse of :func:`polar_angle`, which
    rises once round the turn on a surface star-shaped about z)."""
    grid = np.linspace(0.0, 2 * np.pi, 1441)
    polar = polar_angle(surface, grid, np.full(grid.size, z_mm))
    ok = np.isfinite(polar)  # an outline may have no surface at some angles of this height
    if ok.sum() < 2:
        return np.asarray(polar_rad, dtype=float) % (2 * np.pi)
    grid, polar = grid[ok], np.unwrap(polar[ok])
    polar -= 2 * np.pi * np.floor(polar[0] / (2 * np.pi))
    target = np.asarray(polar_rad, dtype=float) % (2 * np.pi)
    target = np.where(target < polar[0], target + 2 * np.pi, target)
    return np.interp(target, polar, grid) % (2 * np.pi)


def _fill_angles(radius: NDArray[np.float64]) -> NDArray[np.float64]:
    """Close gaps of a few angles in each height's row (a sparse sampling), periodically; wider gaps stay NaN."""
    out = radius.copy()
    n = radius.shape[1]
    for row in out:
        ok = np.isfinite(row)
        if ok.sum() < 3 or ok.all():
            continue
        idx = np.flatnonzero(ok)
        missing = np.flatnonzero(~ok)
        ext = np.concatenate([idx - n, idx, idx + n])
        vals = np.tile(row[idx], 3)
        pos = np.searchsorted(ext, missing)
        gap = ext[pos] - ext[pos - 1]
        fill = missing[gap <= max(3, n // 36)]
        row[fill] = np.interp(fill, ext, vals)
    return out


__all__ = ["Ellipsoid", "EllipticCylinder", "Outline", "TapeSurface", "address_angle", "polar_angle", "shape_from_text"]
