"""The three phantoms of the paper's experiments (A bench, B Zeego/Cho, C Pheno torso).

Object frame: z is the rotation axis (up), x lateral, y front-to-back; millimetres. Each
primitive's attenuation adds to what is around it, so inner structures carry the difference
to their surroundings. Everything fits the default bench field of view (~270 mm at the isocenter).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from orbitct.phantoms.anatomy import CLUTTER, with_anatomy
from orbitct.phantoms.materials import mu_of
from orbitct.phantoms.phantom import Phantom
from orbitct.phantoms.primitives import PhantomError, Primitive, cylinder, ellipsoid, sphere
from orbitct.reference_bench import BB_DIAMETER_MM

EXPERIMENTS = ("A", "B", "C")
#: where BBs can be taped on each experiment's object: the side of an elliptic cylinder about z less 10 mm at
#: either end, (semi-axis x, semi-axis y, lowest and highest BB centre height), mm; C's own ten BBs sit within
#: 70 mm of the torso's middle
BB_SURFACES = {"A": (75.0, 75.0, -80.0, 80.0), "B": (60.0, 60.0, -55.0, 55.0), "C": (120.0, 90.0, -100.0, 100.0)}
Z = np.array([0.0, 0.0, 1.0])


def _bbs(centers: np.ndarray, diameter_mm: float, mu: float | None = None, displaces: str = "") -> list[Primitive]:
    return [
        sphere(c, diameter_mm / 2, material="steel", mu=mu, label=f"bb{k}", displaces=displaces)
        for k, c in enumerate(centers)
    ]


def _pack_spheres(
    rng: np.random.Generator,
    n: int,
    r_range: tuple[float, float],
    cyl_radius: float,
    z_range: tuple[float, float],
    keep_out: tuple[float, float, float],
    batch: int = 256,
) -> list[tuple[np.ndarray, float]]:
    """Up to ``n`` non-overlapping spheres (largest first) in a z-cylinder, away from the column ``keep_out = (x, y, r)``."""
    radii = np.sort(rng.uniform(*r_range, n))[::-1]
    cs = np.zeros((0, 3))
    rs = np.zeros(0)
    kx, ky, kr = keep_out
    for r in radii:
        rho = (cyl_radius - r) * np.sqrt(rng.uniform(size=batch))
        a = rng.uniform(0, 2 * np.pi, batch)
        c = np.stack([rho * np.cos(a), rho * np.sin(a), rng.uniform(z_range[0] + r, z_range[1] - r, batch)], axis=1)
        ok = np.hypot(c[:, 0] - kx, c[:, 1] - ky) >= kr + r
        if len(rs):
            ok &= (np.linalg.norm(c[:, None] - cs[None], axis=-1) >= rs + r + 0.5).all(axis=1)
        hit = np.flatnonzero(ok)
        if hit.size:
            cs = np.vstack([cs, c[hit[0]]])
            rs = np.append(rs, r)
    return list(zip(cs, rs))


def _cervical_spine() -> list[Primitive]:
    """Seven cervical vertebrae of dense 3D-printing material along z, with a slight lordosis."""
    out: list[Primitive] = []
    for k, z in enumerate(np.linspace(66.0, -66.0, 7)):
        y0 = -6.0 + 5.0 * np.cos(np.pi * z / 150.0)
        name = f"C{k + 1}"
        out.append(cylinder((0, y0, z), Z, 9.0, 13.0, radius_b_mm=7.5, material="bone_print", label=f"{name} body"))
        out.append(ellipsoid((0, y0 + 17, z), (14.0, 4.5, 5.0), material="bone_print", label=f"{name} arch"))
        for s in (-1, 1):
            out.append(ellipsoid((s * 13.0, y0 + 9, z), (4.5, 6.0, 6.0), material="bone_print", label=f"{name} mass"))
        out.append(ellipsoid((0, y0 + 27, z - 2), (2.5, 8.0, 3.5), material="bone_print", label=f"{name} spinous"))
    return out


def phantom_a(seed: int = 0) -> Phantom:
    """Experiment A: acrylic container of polystyrene spheres around a printed spine, 8 steel BBs in a rough spiral."""
    rng = np.random.default_rng([seed, 65])
    acr = mu_of("acrylic")
    prims = [
        cylinder((0, 0, 0), Z, 75.0, 180.0, material="acrylic", label="container wall"),
        cylinder((0, 0, 2.0), Z, 72.0, 176.0, material="air", mu=-acr, label="container cavity", displaces="acrylic"),
    ]
    spine = _cervical_spine()
    prims += spine
    for k, (c, r) in enumerate(_pack_spheres(rng, 320, (4.0, 14.0), 72.0, (-86.0, 90.0), (0.0, 4.0, 30.0))):
        prims.append(sphere(c, r, material="polystyrene", label=f"clutter{k}"))
    d = BB_DIAMETER_MM
    base = rng.uniform(0, 360)
    az = np.radians(base + 45.0 * np.arange(8) + rng.uniform(-10, 10, 8))
    z = -63.0 + 18.0 * np.arange(8) + rng.uniform(-4, 4, 8)
    rr = 75.0 + d / 2
    bbs = np.stack([rr * np.cos(az), rr * np.sin(az), z], axis=1)
    prims += _bbs(bbs, d)
    return Phantom(
        "A",
        tuple(prims),
        bbs,
        d,
        "bench phantom: acrylic cylinder (150 mm) filled with polystyrene spheres around a printed cervical spine, "
        "eight 3.17 mm steel BBs taped on the side in a rough spiral",
    )


def phantom_b(seed: int = 0) -> Phantom:
    """Experiment B: Cho-style acrylic cylinder with two rings of 8 steel BBs and a 0.13 mm tungsten wire on its axis."""
    rng = np.random.default_rng([seed, 66])
    acr = mu_of("acrylic")
    prims = [
        cylinder((0, 0, 0), Z, 60.0, 130.0, material="acrylic", label="body"),
        cylinder((0, 0, 0), Z, 45.0, 130.0 + 1e-3, material="air", mu=-acr, label="bore", displaces="acrylic"),
    ]
    d = BB_DIAMETER_MM
    centers = []
    for ring, z in enumerate((-45.0, 45.0)):
        az = np.radians(45.0 * np.arange(8) + 22.5 * ring)
        c = np.stack([52.5 * np.cos(az), 52.5 * np.sin(az), np.full(8, z)], axis=1)
        centers.append(c + rng.uniform(-0.2, 0.2, c.shape))  # manufacturing tolerance
    bbs = np.concatenate(centers)
    prims += _bbs(bbs, d, mu=mu_of("steel") - acr, displaces="acrylic")
    prims.append(cylinder((0, 0, 0), Z, 0.065, 130.0, material="tungsten", label="wire"))
    return Phantom(
        "B",
        tuple(prims),
        bbs,
        d,
        "Cho-style calibration cylinder (120 mm acrylic tube) with 16 steel BBs in two rings "
        "and a 0.13 mm tungsten wire along the axis",
    )


def _lumbar_spine(tissue: float) -> list[Primitive]:
    cort, trab = mu_of("cortical") - tissue, mu_of("trabecular") - tissue
    out: list[Primitive] = []
    for k, z in enumerate((76.0, 38.0, 0.0, -38.0, -76.0)):
        n = f"L{k + 1}"
        out.append(
            cylinder(
                (0, 10, z),
                Z,
                24.0,
                26.0,
                radius_b_mm=17.0,
                material="cortical",
                mu=cort,
                label=f"{n} body",
                displaces="tissue",
            )
        )
        out.append(
            cylinder(
                (0, 10, z),
                Z,
                22.5,
                23.0,
                radius_b_mm=15.5,
                material="trabecular",
                mu=trab - cort,
                label=f"{n} body core",
                displaces="cortical",
            )
        )
        for s in (-1, 1):
            out.append(
                cylinder(
                    (s * 14.0, 36, z),
                    (0, 1, 0),
                    4.5,
                    20.0,
                    radius_b_mm=7.0,
                    ref=(1, 0, 0),
                    material="cortical",
                    mu=cort,
                    label=f"{n} pedicle",
                    displaces="tissue",
                )
            )
            out.append(
                ellipsoid(
                    (s * 27.0, 40, z),
                    (12.0, 4.0, 5.0),
                    material="cortical",
                    mu=cort,
                    label=f"{n} transverse",
                    displaces="tissue",
                )
            )
        out.append(
            ellipsoid(
                (0, 50, z), (17.0, 5.0, 9.0), material="cortical", mu=cort, label=f"{n} lamina", displaces="tissue"
            )
        )
        out.append(
            ellipsoid(
                (0, 63, z - 4), (4.0, 11.0, 8.0), material="cortical", mu=cort, label=f"{n} spinous", displaces="tissue"
            )
        )
    return out


def _screws(tissue: float) -> list[Primitive]:
    """Four titanium pedicle screws: L2 left, L3 both sides, L4 right (shaft + tulip head)."""
    ti = mu_of("titanium")
    out: list[Primitive] = []
    for vert, z, side in (("L2", 38.0, -1), ("L3", 0.0, -1), ("L3", 0.0, 1), ("L4", -38.0, 1)):
        entry = np.array([side * 17.0, 50.0, z])
        a = np.radians(15.0)
        direction = np.array([-side * np.sin(a), -np.cos(a), 0.0])  # forward and towards the midline
        out.append(
            cylinder(
                entry + 22.5 * direction,
                direction,
                3.25,
                45.0,
                material="titanium",
                mu=ti - mu_of("trabecular"),
                label=f"{vert} screw",
                displaces="trabecular",
            )
        )
        out.append(
            cylinder(
                entry - 7.0 * direction,
                direction,
                5.5,
                12.0,
                material="titanium",
                mu=ti - tissue,
                label=f"{vert} screw head",
                displaces="tissue",
            )
        )
    return out


def phantom_c(seed: int = 0) -> Phantom:
    """Experiment C: torso with lumbar spine, four titanium pedicle screws in L2-L4, ten 2 mm BBs on the skin."""
    rng = np.random.default_rng([seed, 67])
    tissue = mu_of("tissue")
    a, b = 120.0, 90.0
    prims = [cylinder((0, 0, 0), Z, a, 220.0, radius_b_mm=b, ref=(1, 0, 0), material="tissue", label="torso")]
    for s in (-1, 1):
        prims.append(
            ellipsoid(
                (s * 55.0, -5.0, 75.0),
                (38.0, 45.0, 30.0),
                material="lung",
                mu=mu_of("lung") - tissue,
                label="lung",
                displaces="tissue",
            )
        )
        prims.append(
            ellipsoid((s * 45.0, 25.0, -30.0), (22.0, 14.0, 32.0), material="tissue", mu=0.002, label="kidney")
        )
    prims += _lumbar_spine(tissue)
    prims += _screws(tissue)
    d = 2.0
    bbs = np.zeros((0, 3))
    for _ in range(5000):
        if len(bbs) == 10:
            break
        al = rng.uniform(0, 2 * np.pi)
        z = rng.uniform(-70.0, 70.0)
        p = np.array([a * np.cos(al), b * np.sin(al), 0.0])
        nrm = np.array([np.cos(al) / a, np.sin(al) / b, 0.0])
        c = p + nrm / np.linalg.norm(nrm) * (d / 2) + np.array([0, 0, z])
        if len(bbs) and (np.linalg.norm(bbs - c, axis=1) < 30.0).any():
            continue
        bbs = np.vstack([bbs, c])
    prims += _bbs(bbs, d)
    return Phantom(
        "C",
        tuple(prims),
        bbs,
        d,
        "torso (240 x 180 mm) with a lumbar spine, four titanium pedicle screws in L2-L4 "
        "and ten 2 mm steel BBs taped to the skin",
    )


def experiment_phantom(name: str, seed: int = 0, *, clutter: str = "none") -> Phantom:
    """Phantom of experiment ``'A'``, ``'B'`` or ``'C'``; marker positions and clutter vary with ``seed``.
    ``clutter='anatomy'`` adds a patient's anatomy to C's torso (:mod:`orbitct.phantoms.anatomy`)."""
    key = str(name).upper()
    if key not in EXPERIMENTS:
        raise PhantomError(f"unknown experiment {name!r}; known experiments are {list(EXPERIMENTS)}")
    if clutter not in CLUTTER:
        raise PhantomError(f"unknown clutter {clutter!r}; choose from {list(CLUTTER)}")
    return _cached(key, int(seed), clutter)


@lru_cache(maxsize=16)
def _cached(key: str, seed: int, clutter: str) -> Phantom:
    phantom = {"A": phantom_a, "B": phantom_b, "C": phantom_c}[key](seed)
    return with_anatomy(phantom, seed) if clutter == "anatomy" else phantom
