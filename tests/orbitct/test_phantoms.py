"""Analytic phantoms: exact chords (vs numeric ray marching), JSON, experiment phantoms, voxelizer."""

import numpy as np
import pytest

from orbitct.phantoms import (
    Phantom,
    PhantomError,
    Primitive,
    cylinder,
    ellipsoid,
    experiment_phantom,
    frame_from_axis,
    sphere,
    voxelize,
)
from orbitct.rotations import rotvec_to_matrix
from orbitct.simulator import SimulatedBench

RNG = np.random.default_rng(2024)


def _march(prim: Primitive, o: np.ndarray, d: np.ndarray, inside_t: float) -> float:
    """Chord by numeric ray marching: step out of the (convex) shape both ways, then bisect the boundary."""

    def inside(t: float) -> bool:
        return bool(prim.contains((o + t * d)[None])[0])

    ends = []
    for sgn in (-1.0, 1.0):
        lo, step = inside_t, 0.05
        hi = lo + sgn * step
        while inside(hi):
            lo, hi = hi, hi + sgn * step
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if inside(mid) else (lo, mid)
            if abs(hi - lo) < 1e-13:
                break
        ends.append(0.5 * (lo + hi))
    return abs(ends[1] - ends[0]) * np.linalg.norm(d)


def _random_primitives() -> list[Primitive]:
    out = []
    for _k in range(6):
        R = rotvec_to_matrix(RNG.normal(size=3))
        c = RNG.uniform(-30, 30, 3)
        s = RNG.uniform(2, 25, 3)
        out.append(Primitive("ellipsoid", c, s, R, 1.0))
        out.append(Primitive("cylinder", c, s, R, 1.0))
    out.append(sphere((1, 2, 3), 1.585, mu=1.0))
    out.append(cylinder((0, 0, 0), (0.2, 0.1, 1.0), 0.065, 130.0, mu=1.0))
    return out


@pytest.mark.parametrize("prim", _random_primitives(), ids=lambda p: p.kind)
def test_chords_match_ray_marching(prim: Primitive) -> None:
    # lines through interior points (local radius <= 0.8) in random directions, from far away
    n = 12
    y = RNG.normal(size=(n, 3))
    y *= (0.8 * RNG.uniform(0, 1, n) ** (1 / 3) / np.linalg.norm(y, axis=1))[:, None]
    if prim.kind == "cylinder":
        y[:, 2] = RNG.uniform(-0.8, 0.8, n)
    p_in = prim.center + (y * prim.semi_axes) @ prim.rotation.T
    d = RNG.normal(size=(n, 3)) * RNG.uniform(0.5, 3.0, (n, 1))
    origins = p_in - 7.3 * d
    exact = prim.chords(origins, d)
    ref = np.array([_march(prim, origins[i], d[i], 7.3) for i in range(n)])
    assert np.allclose(exact, ref, rtol=1e-6, atol=0)


def test_chord_special_directions() -> None:
    c = cylinder((0, 0, 0), (0, 0, 1), 10.0, 40.0, mu=1.0)
    # along the axis: the full length; parallel to the caps: the full diameter; outside: zero
    assert np.isclose(c.chords([[3, 4, -100]], [[0, 0, 1]])[0], 40.0)
    assert np.isclose(c.chords([[-50, 0, 19.9]], [[1, 0, 0]])[0], 20.0)
    assert c.chords([[-50, 0, 20.1]], [[1, 0, 0]])[0] == 0.0
    assert c.chords([[11, 0, -100]], [[0, 0, 1]])[0] == 0.0
    s = sphere((0, 0, 0), 5.0, mu=1.0)
    assert np.isclose(s.chords([[0, 3, -50]], [[0, 0, 2.0]])[0], 8.0)


def test_json_round_trip() -> None:
    p = experiment_phantom("C", seed=4)
    q = Phantom.from_json(p.to_json())
    assert q.name == "C" and len(q.primitives) == len(p.primitives)
    assert np.array_equal(q.markers_xyz, p.markers_xyz) and q.marker_diameter_mm == 2.0
    pts = RNG.uniform(-120, 120, (500, 3))
    assert np.array_equal(q.attenuation_at(pts), p.attenuation_at(pts))
    import json

    assert Phantom.from_json(json.dumps(p.to_json())).n_markers == 10
    with pytest.raises(PhantomError, match="'primitives' list"):
        Phantom.from_json({"name": "x"})


@pytest.mark.parametrize(
    "name, n_bb, diameter, n_metal_extra", [("A", 8, 3.17, 0), ("B", 16, 3.17, 1), ("C", 10, 2.0, 8)]
)
def test_experiment_phantoms(name: str, n_bb: int, diameter: float, n_metal_extra: int) -> None:
    p = experiment_phantom(name, seed=1)
    assert p.n_markers == n_bb and p.marker_diameter_mm == diameter
    assert len(p.metal_indices) == n_bb + n_metal_extra
    bbs = [q for q in p.primitives if q.label.startswith("bb")]
    assert np.allclose([b.center for b in bbs], p.markers_xyz)
    assert all(np.allclose(b.semi_axes, diameter / 2) and b.material == "steel" for b in bbs)
    # BBs are separated and sit where they are no further inside than their radius
    dist = np.linalg.norm(p.markers_xyz[:, None] - p.markers_xyz[None], axis=-1) + np.eye(n_bb) * 1e9
    assert dist.min() > 4 * diameter
    # fits the bench field of view (~279 mm at the isocenter) laterally, and vertically with room for tilt
    lo, hi = p.bounding_box()
    fov = SimulatedBench().fov_mm
    assert np.maximum(-lo[:2], hi[:2]).max() < fov / 2
    assert max(-lo[2], hi[2]) < fov / 2
    assert p.without_metal().metal_indices.size == 0


def test_phantom_a_varies_with_seed_and_wire_in_b() -> None:
    a1, a2 = experiment_phantom("A", 1), experiment_phantom("A", 2)
    assert not np.allclose(a1.markers_xyz, a2.markers_xyz)
    assert np.array_equal(experiment_phantom("A", 1).markers_xyz, a1.markers_xyz)
    wire = next(q for q in experiment_phantom("B").primitives if q.label == "wire")
    assert wire.material == "tungsten" and np.isclose(2 * wire.semi_axes[0], 0.13)
    with pytest.raises(PhantomError, match="known experiments are"):
        experiment_phantom("D")


def test_voxelize_volume_and_index_order() -> None:
    prims = (
        sphere((10.0, -4.0, 6.0), 5.0, mu=2.0),
        cylinder((-8.0, 6.0, -4.0), (1, 1, 0), 3.0, 12.0, mu=1.0),
        ellipsoid((0, 0, 0), (2.0, 3.0, 4.0), rotation=frame_from_axis((0, 1, 1)), mu=0.5),
    )
    p = Phantom("t", prims)
    vox = 0.5
    shape = (56, 60, 64)
    origin = (-16 + vox / 2, -15 + vox / 2, -14 + vox / 2)
    v = voxelize(p, shape, vox, origin, supersample=4)
    assert v.dtype == np.float32 and v.shape == shape
    expect = sum(q.mu * q.volume_mm3() for q in prims)
    assert v.sum() * vox**3 == pytest.approx(expect, rel=0.01)
    # voxel centre of the sphere: index z, y, x
    iz, iy, ix = (np.array([6.0, -4.0, 10.0]) - np.array(origin)[::-1]) / vox
    assert v[int(round(iz)), int(round(iy)), int(round(ix))] == pytest.approx(2.0)
    # exact inside/outside away from surfaces
    zz, yy, xx = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    pts = np.stack([xx, yy, zz], -1).reshape(-1, 3) * vox + np.array(origin)
    exact = p.attenuation_at(pts).reshape(shape)
    assert np.mean(np.isclose(v, exact, atol=1e-6)) > 0.97


def test_voxelize_thin_wire_keeps_its_mass() -> None:
    w = Phantom("w", (cylinder((0, 0, 0), (0, 0, 1), 0.065, 20.0, mu=7.0),))
    mass = 7.0 * np.pi * 0.065**2 * 20
    for origin in ((-4.0, -4.0, -9.5), (-3.5, -3.5, -9.5), (-3.7, -3.2, -9.5)):  # wire on centres, edges, anywhere
        v = voxelize(w, (20, 9, 9), 1.0, origin)
        assert v.sum() == pytest.approx(mass, rel=1e-4)
    v = voxelize(w, (40, 16, 16), 0.5, (-3.75, -3.75, -9.75))
    assert v.sum() * 0.125 == pytest.approx(mass, rel=1e-4)
    tilted = Phantom("t", (cylinder((1, 2, 0), (0.3, 0.5, 1), 0.065, 20.0, mu=7.0),))
    v = voxelize(tilted, (40, 40, 40), 0.5, (-9.75, -9.75, -9.75))
    assert v.sum() * 0.125 == pytest.approx(mass, rel=1e-4)
    # the mass sits on the voxels the axis runs through
    assert v[20, 24, 22] > 0 and v[20, 10, 10] == 0


def test_voxelize_errors() -> None:
    p = Phantom("s", (sphere((0, 0, 0), 1.0, mu=1.0),))
    with pytest.raises(PhantomError, match="3 positive sizes"):
        voxelize(p, (4, 4), 1.0, (0, 0, 0))
    with pytest.raises(PhantomError, match="voxel_mm must be > 0"):
        voxelize(p, (4, 4, 4), 0.0, (0, 0, 0))
