"""Linear attenuation coefficients (1/mm) at an effective energy of about 60 keV (90 kV, filtered), and the
elemental make-up of each material, from which a polychromatic beam scales them with energy."""

from __future__ import annotations

#: the energy at which :data:`MU_PER_MM` holds (keV)
REFERENCE_KEV = 60.0

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

_BONE = "H .034 C .155 N .042 O .435 Na .001 Mg .002 P .103 S .003 Ca .225"
#: mass fractions by element (ICRU 44 / NIST compositions for the tissues; the printed spine as compact bone;
#: Ti-6Al-4V screws; AISI 52100 chrome-steel BBs)
COMPOSITION: dict[str, dict[str, float]] = {
    name: {el: float(f) for el, f in zip(text.split()[::2], text.split()[1::2], strict=True)}
    for name, text in {
        "air": "N .755 O .232 Ar .013",
        "water": "H .1119 O .8881",
        "tissue": "H .101 C .111 N .026 O .762",
        "fat": "H .114 C .598 N .007 O .281",
        "lung": "H .103 C .105 N .031 O .749 P .002 S .003 Cl .003 K .004",
        "acrylic": "H .0805 C .5998 O .3197",
        "polystyrene": "H .0774 C .9226",
        "bone_print": _BONE,
        "trabecular": "H .085 C .404 N .028 O .367 Na .001 Mg .001 P .034 S .002 Cl .002 K .001 Ca .074 Fe .001",
        "cortical": _BONE,
        "titanium": "Ti .90 Al .06 V .04",
        "steel": "Fe .975 Cr .015 C .010",
        "tungsten": "W 1",
    }.items()
}

METALS: frozenset[str] = frozenset({"titanium", "steel", "tungsten"})


def mu_of(material: str) -> float:
    """Attenuation of a named material (1/mm)."""
    try:
        return MU_PER_MM[material]
    except KeyError:
        raise ValueError(f"unknown material {material!r}; known materials are {sorted(MU_PER_MM)}") from None
