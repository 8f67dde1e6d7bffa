"""Anatomy-like clutter for experiment C's torso: what a patient adds to a clean phantom in front of the BBs.

A subcutaneous fat layer under the skin the BBs are taped to, fat lobules through the soft tissue, the aorta and
vena cava, the lowest two pairs of ribs (cortical shell, marrow core), a steel guide wire by the spine and three ECG
electrodes with their lead wires on the skin. Placed at random from the phantom's seed; every piece names the
material it displaces, so a polychromatic beam treats it right.
"""

from __future__ import annotations

import numpy as np

from orbitct.phantoms.materials import mu_of
from orbitct.phantoms.phantom import Phantom
from orbitct.phantoms.primitives import PhantomError, Primitive, cylinder, ellipsoid

TORSO_MM = (120.0, 90.0, 110.0)  # experiment C's torso: semi-axes x, y and half its height
CLUTTER = ("none", "anatomy")
Z = (0.0, 0.0, 1.0)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.standard_normal(4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _fat_layer() -> list[Primitive]:
    """Subcutaneous fat: 12 mm at the sides and front, thinner (8 mm) over the back, under the whole skin."""
    a, b, h = TORSO_MM
    return [
        cylinder((0, 0, 0), Z, a - 1.0, 2 * h - 2, radius_b_mm=b - 1.0, material="fat", displaces="tissue",
                 label="subcutaneous fat"),
        cylinder((0, 2.0, 0), Z, a - 13.0, 2 * h - 2.01, radius_b_mm=b - 11.0, material="tissue", displaces="fat",
                 label="under the fat"),
    ]  # fmt: skip


def _lobules(rng: np.random.Generator, n: int = 180) -> list[Primitive]:
    """Fat lobules in the soft tissue, away from the spine and the lungs (semi-axes 2-14 mm, any orientation)."""
    a, b, h = TORSO_MM
    out: list[Primitive] = []
    while len(out) < n:
        c = rng.uniform((-a, -b, -h + 12), (a, b, h - 12))
        s = rng.uniform(3.0, 12.0, 3) * np.array([1.0, 0.8, 1.2])
        if (c[0] / (a - 16 - s.max())) ** 2 + (c[1] / (b - 14 - s.max())) ** 2 > 1:
            continue  # inside the fat layer's inner edge
        if abs(c[0]) < 45 + s.max() and c[1] > -10 - s.max():
            continue  # spine, pedicles and transverse processes
        if ((abs(c[0]) - 55) / 38) ** 2 + ((c[1] + 5) / 45) ** 2 + ((c[2] - 75) / 30) ** 2 < 1.3:
            continue  # lungs
        out.append(ellipsoid(c, s, rotation=_random_rotation(rng), material="fat", displaces="tissue",
                             label=f"fat lobule {len(out)}"))  # fmt: skip
    return out


def _vessels() -> list[Primitive]:
    """Aorta and inferior vena cava in front of the spine (blood slightly denser than soft tissue)."""
    blood = 0.0006
    _, _, h = TORSO_MM
    return [
        cylinder((-18, -22, 0), Z, 11.0, 2 * h - 4, material="tissue", mu=blood, label="aorta"),
        cylinder((22, -20, 0), Z, 10.0, 2 * h - 4, radius_b_mm=7.0, material="tissue", mu=blood, label="vena cava"),
    ]


def _ribs() -> list[Primitive]:
    """Ribs 11 and 12 on both sides: from beside the spine round the back and the flank, each in 9 segments of an
    elliptic bone (5.5 x 3.5 mm cortical shell round a marrow core), falling 3 mm per segment towards the front."""
    a, b, _ = TORSO_MM
    out: list[Primitive] = []
    for rib, z0, reach in (("rib 11", 100.0, 1.9), ("rib 12", 72.0, 1.6)):
        for side in (-1, 1):
            angles = np.linspace(np.pi / 2 + 0.35, np.pi / 2 + reach, 10)  # from the back (+y) towards the flank
            pts = np.stack(
                [side * -(a - 22) * np.cos(angles), (b - 20) * np.sin(angles), z0 - 3.0 * np.arange(10)], axis=1
            )
            for k in range(9):
                p, q = pts[k], pts[k + 1]
                axis = q - p
                length = float(np.linalg.norm(axis))
                mid = (p + q) / 2
                ref = np.cross(axis, Z)  # the rib's flat side faces outwards
                cort = mu_of("cortical") - mu_of("tissue")
                out.append(cylinder(mid, axis, 5.5, length, radius_b_mm=3.5, ref=ref, material="cortical", mu=cort,
                                    displaces="tissue", label=f"{rib} {'left' if side < 0 else 'right'} {k}"))  # fmt: skip
                core = mu_of("trabecular") - mu_of("cortical")
                out.append(cylinder(mid, axis, 4.0, length, radius_b_mm=2.0, ref=ref, material="trabecular", mu=core,
                                    displaces="cortical", label=f"{rib} marrow {k}"))  # fmt: skip
    return out


def _metal(rng: np.random.Generator) -> list[Primitive]:
    """A 1.6 mm steel guide wire by L4, three ECG electrodes (10 mm steel snaps) on the chest wall and their
    0.6 mm lead wires running up along the skin and off the top."""
    a, b, _ = TORSO_MM
    steel = mu_of("steel") - mu_of("tissue")
    direction = np.array([0.25, -1.0, 0.35])
    out = [cylinder((30, 55, -40), direction, 0.8, 90.0, material="steel", mu=steel, displaces="tissue",
                    label="guide wire")]  # fmt: skip
    for k, (al, z) in enumerate(((-2.2, 95.0), (-1.6, 90.0), (-1.0, 96.0))):  # on the front (-y), near the top
        al += rng.uniform(-0.1, 0.1)
        nrm = np.array([np.cos(al) / a, np.sin(al) / b, 0.0])
        nrm /= np.linalg.norm(nrm)
        skin = np.array([a * np.cos(al), b * np.sin(al), z])
        out.append(cylinder(skin + 1.0 * nrm, nrm, 5.0, 2.0, material="steel", label=f"ECG electrode {k}"))
        lead_end = skin + 4.0 * nrm + np.array([0.0, 0.0, 60.0])
        start = skin + 3.0 * nrm
        out.append(cylinder((start + lead_end) / 2, lead_end - start, 0.3, float(np.linalg.norm(lead_end - start)),
                            material="steel", label=f"ECG lead {k}"))  # fmt: skip
    return out


def with_anatomy(phantom: Phantom, seed: int = 0) -> Phantom:
    """Experiment C's torso with anatomy-like clutter added (BBs and everything else as they were)."""
    if phantom.name != "C":
        raise PhantomError(f"anatomy-like clutter is made for experiment C's torso, not experiment {phantom.name}")
    rng = np.random.default_rng([seed, 68])
    extra = _fat_layer() + _lobules(rng) + _vessels() + _ribs() + _metal(rng)
    return Phantom(
        phantom.name,
        phantom.primitives + tuple(extra),
        phantom.markers_xyz,
        phantom.marker_diameter_mm,
        phantom.description + "; with anatomy-like clutter (subcutaneous fat, fat lobules, aorta and vena cava, "
        "ribs 11 and 12, a steel guide wire, three ECG electrodes and leads)",
    )
