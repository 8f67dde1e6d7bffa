"""Linear attenuation coefficients (1/mm) at an effective energy of about 60 keV (90 kV, filtered)."""

from __future__ import annotations

MU_PER_MM: dict[str, float] = {
    "air": 0.0,
    "water": 0.0206,
    "tissue": 0.0200,  # soft tissue
    "fat": 0.0180,
    "lung": 0.0060,
    "acrylic": 0.0228,  # PMMA container walls, Cho phantom body
    "polystyrene": 0.0196,  # clutter spheres
    "bone_print": 0.0420,  # dense 3D-printed spine stand-in
    "trabecular": 0.0300,
    "cortical": 0.0600,
    "titanium": 0.1900,  # pedicle screws
    "steel": 0.8000,  # BBs
    "tungsten": 7.0000,  # thin wire
}

METALS: frozenset[str] = frozenset({"titanium", "steel", "tungsten"})


def mu_of(material: str) -> float:
    """Attenuation of a named material (1/mm)."""
    try:
        return MU_PER_MM[material]
    except KeyError:
        raise ValueError(f"unknown material {material!r}; known materials are {sorted(MU_PER_MM)}") from None
