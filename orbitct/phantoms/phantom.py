"""A phantom: primitives whose attenuations add, plus the marker (BB) centres it carries."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbitct.phantoms.chords import weighted_chord_sum
from orbitct.phantoms.primitives import PhantomError, Primitive


@dataclass(frozen=True)
class PackedPrimitives:
    """Primitive parameters as contiguous arrays for the numba kernels."""

    kind: NDArray[np.int64]
    center: NDArray[np.float64]
    rotation: NDArray[np.float64]
    semi_axes: NDArray[np.float64]
    mu: NDArray[np.float64]
    corners: NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Phantom:
    """Analytic phantom: ``primitives`` (attenuations add where they overlap) and ``markers_xyz`` (K, 3) mm."""

    name: str
    primitives: tuple[Primitive, ...]
    markers_xyz: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    marker_diameter_mm: float | None = None
    description: str = ""

    def __post_init__(self) -> None:
        prims = tuple(self.primitives)
        if not prims:
            raise PhantomError("a phantom needs at least one primitive")
        if not all(isinstance(p, Primitive) for p in prims):
            raise PhantomError("primitives must all be Primitive objects")
        m = np.array(self.markers_xyz, dtype=float).reshape(-1, 3)
        m.setflags(write=False)
        object.__setattr__(self, "primitives", prims)
        object.__setattr__(self, "markers_xyz", m)

    @property
    def n_markers(self) -> int:
        """Number of markers (BBs)."""
        return int(self.markers_xyz.shape[0])

    @cached_property
    def packed(self) -> PackedPrimitives:
        """Arrays for the projection and voxelisation kernels."""
        P = self.primitives
        return PackedPrimitives(
            kind=np.array([p.kind_id for p in P], dtype=np.int64),
            center=np.array([p.center for p in P]),
            rotation=np.array([p.rotation for p in P]),
            semi_axes=np.array([p.semi_axes for p in P]),
            mu=np.array([p.mu for p in P]),
            corners=np.array([p.corners() for p in P]),
        )

    @cached_property
    def by_material(self) -> dict[tuple[str, str], Phantom]:
        """The primitives grouped by ``(material, displaces)``, each group as a phantom of its own."""
        keys = [(p.material, p.displaces) for p in self.primitives]
        return {k: self.subset([key == k for key in keys]) for k in dict.fromkeys(keys)}

    @property
    def metal_indices(self) -> NDArray[np.intp]:
        """Indices of metal primitives (BBs, screws, wires)."""
        return np.array([i for i, p in enumerate(self.primitives) if p.is_metal], dtype=np.intp)

    def with_markers(self, xyz: ArrayLike, diameter_mm: float | None = None) -> Phantom:
        """The same object with its BBs (primitives labelled ``bb<k>``) replaced by steel balls at ``xyz`` (K, 3)."""
        from orbitct.phantoms.primitives import sphere

        d = float(diameter_mm if diameter_mm is not None else self.marker_diameter_mm or 0.0)
        if not d > 0:
            raise PhantomError("with_markers needs the BB diameter (the phantom has none)")
        centres = np.array(xyz, dtype=float).reshape(-1, 3)
        keep = tuple(p for p in self.primitives if not str(p.label).startswith("bb"))
        bbs = tuple(sphere(c, d / 2, material="steel", label=f"bb{k}") for k, c in enumerate(centres))
        return Phantom(self.name, keep + bbs, centres, d, self.description)

    def subset(self, keep: ArrayLike, name: str | None = None) -> Phantom:
        """Phantom of the primitives selected by index or boolean mask (markers kept as they are)."""
        idx = np.arange(len(self.primitives))[np.asarray(keep)]
        return Phantom(
            name or self.name,
            tuple(self.primitives[i] for i in idx),
            self.markers_xyz,
            self.marker_diameter_mm,
            self.description,
        )

    def without_metal(self) -> Phantom:
        """The phantom with every metal primitive removed (reference for metal-artifact studies)."""
        return self.subset([not p.is_metal for p in self.primitives], f"{self.name}-nometal")

    def bounding_box(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Lower and upper corners (mm) of a box holding every primitive."""
        c = self.packed.corners.reshape(-1, 3)
        return c.min(axis=0), c.max(axis=0)

    def attenuation_at(self, points: ArrayLike) -> NDArray[np.float64]:
        """Exact attenuation (1/mm) at points ``(K, 3)``."""
        pts = np.atleast_2d(np.asarray(points, float))
        out = np.zeros(len(pts))
        for p in self.primitives:
            out += p.mu * p.contains(pts)
        return out

    def line_integral(self, origins: ArrayLike, directions: ArrayLike) -> NDArray[np.float64]:
        """Exact line integrals along lines ``(K, 3)`` (no detector involved)."""
        pk = self.packed
        return weighted_chord_sum(pk.kind, pk.center, pk.rotation, pk.semi_axes, pk.mu, origins, directions)

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON description (stored as ``/truth@phantom_json`` in simulated scans)."""
        return {
            "name": self.name,
            "description": self.description,
            "marker_diameter_mm": self.marker_diameter_mm,
            "markers_xyz_mm": self.markers_xyz.tolist(),
            "primitives": [p.to_json() for p in self.primitives],
        }

    @classmethod
    def from_json(cls, data: dict[str, Any] | str) -> Phantom:
        """Inverse of :meth:`to_json` (accepts the dict or its JSON text)."""
        d = json.loads(data) if isinstance(data, str) else data
        if not isinstance(d, dict) or "primitives" not in d:
            raise PhantomError("phantom JSON must be an object with a 'primitives' list")
        return cls(
            name=str(d.get("name", "")),
            primitives=tuple(Primitive.from_json(p) for p in d["primitives"]),
            markers_xyz=np.asarray(d.get("markers_xyz_mm", []), float).reshape(-1, 3),
            marker_diameter_mm=d.get("marker_diameter_mm"),
            description=str(d.get("description", "")),
        )

    def __repr__(self) -> str:
        lo, hi = self.bounding_box()
        size = " x ".join(f"{x:.0f}" for x in hi - lo)
        return (
            f"Phantom({self.name!r}, {len(self.primitives)} primitives, {self.n_markers} markers, "
            f"{len(self.metal_indices)} metal, extent {size} mm)"
        )
