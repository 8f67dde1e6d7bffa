"""Analytic phantom primitives: spheres, ellipsoids and finite (elliptic) cylinders in any orientation."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbitct.phantoms.chords import CYLINDER, ELLIPSOID, chord_lengths
from orbitct.phantoms.materials import METALS, mu_of

KINDS = {"ellipsoid": ELLIPSOID, "cylinder": CYLINDER}


class PhantomError(ValueError):
    """A primitive or phantom description that is not valid."""


def _frozen(a: ArrayLike, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    arr = np.array(a, dtype=float)
    if arr.shape != shape or not np.isfinite(arr).all():
        raise PhantomError(f"{name}: expected {shape} finite numbers, got {np.shape(a)}")
    arr.setflags(write=False)
    return arr


def frame_from_axis(axis: ArrayLike, ref: ArrayLike | None = None) -> NDArray[np.float64]:
    """Rotation whose third column is ``axis`` (normalised) and first column lies towards ``ref``."""
    w = np.asarray(axis, float)
    n = np.linalg.norm(w)
    if n == 0:
        raise PhantomError("axis must be a non-zero vector")
    w = w / n
    r = (
        np.asarray(ref, float)
        if ref is not None
        else (np.array([1.0, 0, 0]) if abs(w[0]) < 0.9 else np.array([0, 1.0, 0]))
    )
    u = r - w * (r @ w)
    if np.linalg.norm(u) < 1e-9:
        raise PhantomError("ref must not be parallel to axis")
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(w, u), w], axis=1)


@dataclass(frozen=True, eq=False)
class Primitive:
    """Ellipsoid or finite elliptic cylinder; ``mu`` (1/mm) adds to whatever else is there.

    ``semi_axes`` are the ellipsoid semi-axes, or for a cylinder ``(radius_a, radius_b,
    half_length)``; ``rotation`` columns are those local axes in the object frame (mm). A primitive
    inside another names the material it takes the place of in ``displaces`` (its ``mu`` is then the
    difference), so a polychromatic beam scales both with energy.
    """

    kind: str
    center: NDArray[np.float64]
    semi_axes: NDArray[np.float64]
    rotation: NDArray[np.float64]
    mu: float
    material: str = ""
    label: str = ""
    displaces: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise PhantomError(f"primitive kind must be one of {sorted(KINDS)}, got {self.kind!r}")
        object.__setattr__(self, "center", _frozen(self.center, (3,), "center"))
        object.__setattr__(self, "semi_axes", _frozen(self.semi_axes, (3,), "semi_axes"))
        R = _frozen(self.rotation, (3, 3), "rotation")
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
            raise PhantomError("rotation must be a proper rotation matrix")
        object.__setattr__(self, "rotation", R)
        if (self.semi_axes <= 0).any():
            raise PhantomError(f"semi_axes must be > 0 mm, got {self.semi_axes.tolist()}")
        object.__setattr__(self, "mu", float(self.mu))

    @property
    def kind_id(self) -> int:
        """Kernel id (0 ellipsoid, 1 cylinder)."""
        return KINDS[self.kind]

    @property
    def is_metal(self) -> bool:
        """Whether the material is a metal (steel, titanium, tungsten)."""
        return self.material in METALS

    def corners(self) -> NDArray[np.float64]:
        """The 8 corners ``(8, 3)`` of the oriented bounding box."""
        sgn = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=float)
        return self.center + (sgn * self.semi_axes) @ self.rotation.T

    def chords(self, origins: ArrayLike, directions: ArrayLike) -> NDArray[np.float64]:
        """Exact chord lengths (mm) of lines through this primitive."""
        return chord_lengths(self.kind_id, self.center, self.rotation, self.semi_axes, origins, directions)

    def contains(self, points: ArrayLike) -> NDArray[np.bool_]:
        """Whether points ``(K, 3)`` lie inside."""
        y = ((np.atleast_2d(np.asarray(points, float)) - self.center) @ self.rotation) / self.semi_axes
        if self.kind == "ellipsoid":
            return (y**2).sum(axis=1) <= 1.0
        return ((y[:, :2] ** 2).sum(axis=1) <= 1.0) & (np.abs(y[:, 2]) <= 1.0)

    def volume_mm3(self) -> float:
        """Exact volume."""
        a, b, c = self.semi_axes
        return float(4.0 / 3.0 * np.pi * a * b * c if self.kind == "ellipsoid" else np.pi * a * b * 2 * c)

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON description."""
        return {
            "kind": self.kind,
            "center_mm": self.center.tolist(),
            "semi_axes_mm": self.semi_axes.tolist(),
            "rotation": self.rotation.tolist(),
            "mu_per_mm": self.mu,
            "material": self.material,
            "label": self.label,
            **({"displaces": self.displaces} if self.displaces else {}),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Primitive:
        """Inverse of :meth:`to_json`."""
        try:
            return cls(
                d["kind"],
                d["center_mm"],
                d["semi_axes_mm"],
                d["rotation"],
                d["mu_per_mm"],
                d.get("material", ""),
                d.get("label", ""),
                d.get("displaces", ""),
            )
        except KeyError as exc:
            raise PhantomError(f"primitive description lacks {exc.args[0]!r}: {d}") from None


def _vec(values: ArrayLike) -> NDArray[np.float64]:
    return np.asarray(values, dtype=np.float64)


def _mu(mu: float | None, material: str, displaces: str) -> float:
    if mu is not None:
        return float(mu)
    return mu_of(material) - (mu_of(displaces) if displaces else 0.0)


def sphere(
    center: ArrayLike,
    radius_mm: float,
    *,
    material: str = "water",
    mu: float | None = None,
    label: str = "",
    displaces: str = "",
) -> Primitive:
    """A sphere; ``mu`` defaults to the material's attenuation (less that of ``displaces``)."""
    r = np.full(3, float(radius_mm))
    return Primitive("ellipsoid", _vec(center), r, np.eye(3), _mu(mu, material, displaces), material, label, displaces)


def ellipsoid(
    center: ArrayLike,
    semi_axes_mm: ArrayLike,
    *,
    rotation: ArrayLike | None = None,
    material: str = "water",
    mu: float | None = None,
    label: str = "",
    displaces: str = "",
) -> Primitive:
    """An ellipsoid with semi-axes along the columns of ``rotation`` (identity: x, y, z)."""
    R = np.asarray(np.eye(3) if rotation is None else rotation, dtype=float)
    mu_mm = _mu(mu, material, displaces)
    return Primitive("ellipsoid", _vec(center), _vec(semi_axes_mm), R, mu_mm, material, label, displaces)


def cylinder(
    center: ArrayLike,
    axis: ArrayLike,
    radius_mm: float,
    length_mm: float,
    *,
    radius_b_mm: float | None = None,
    ref: ArrayLike | None = None,
    material: str = "water",
    mu: float | None = None,
    label: str = "",
    displaces: str = "",
) -> Primitive:
    """A finite cylinder along ``axis``; elliptic when ``radius_b_mm`` is given (``radius_mm`` towards ``ref``)."""
    rb = radius_mm if radius_b_mm is None else radius_b_mm
    R = frame_from_axis(axis, ref)
    return Primitive(
        "cylinder",
        _vec(center),
        np.array([radius_mm, rb, length_mm / 2.0], dtype=float),
        R,
        _mu(mu, material, displaces),
        material,
        label,
        displaces,
    )
