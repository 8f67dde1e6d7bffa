"""Surfaces the BB planner tapes on: an elliptic cylinder and an ellipsoid by parameters, and a real object's outline
from a prior volume's mask, from a surface mesh, or from a reconstruction in a scan file."""

from __future__ import annotations

import numpy as np
import pytest

from calib.surfaces import (
    Ellipsoid,
    EllipticCylinder,
    Outline,
    address_angle,
    polar_angle,
    shape_from_text,
)

D_MM = 3.0


def _cylinder_mask(radius_mm: float = 60.0, half_height_mm: float = 40.0) -> tuple[np.ndarray, tuple, tuple]:
    voxel = (1.0, 1.0, 1.0)
    origin = (-80.0, -80.0, -60.0)
    z, y, x = np.meshgrid(np.arange(121) - 60.0, np.arange(161) - 80.0, np.arange(161) - 80.0, indexing="ij")
    return (np.hypot(x, y) <= radius_mm) & (np.abs(z) <= half_height_mm), voxel, origin


def test_an_outline_from_a_volume_mask_is_the_cylinder_it_came_from() -> None:
    mask, voxel, origin = _cylinder_mask()
    outline = Outline.from_mask(mask, voxel, origin, source="test")
    assert outline.z_min_mm == pytest.approx(-40.0, abs=2.0) and outline.z_max_mm == pytest.approx(40.0, abs=2.0)
    ang = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    z = np.full(50, 10.0)
    xyz = outline.points(ang, z, D_MM)
    assert np.allclose(np.hypot(xyz[:, 0], xyz[:, 1]), 60.0 + D_MM / 2, atol=1.0) and np.allclose(
        xyz[:, 2], 10.0, atol=0.1
    )
    assert outline.covers(ang, z).all() and not outline.covers(ang[:3], np.full(3, 55.0)).any()
    assert outline.describe()["kind"] == "outline"
    with pytest.raises(ValueError, match="no voxel above the threshold"):
        Outline.from_mask(np.zeros((4, 4, 4), bool), voxel, origin)


def test_an_outline_follows_a_slanted_surface_along_its_normal() -> None:
    """A cone (radius growing with height): the BB sits a radius out along the surface normal, not sideways."""
    rng = np.random.default_rng(0)
    z = rng.uniform(-40, 40, 50_000)
    ang = rng.uniform(0, 2 * np.pi, 50_000)
    r = 50.0 + 0.5 * z  # slope 0.5: the normal leans down by atan(0.5)
    outline = Outline.from_points(np.stack([r * np.cos(ang), r * np.sin(ang), z], -1), z_step_mm=1.0)
    p = outline.points(np.array([0.0]), np.array([0.0]), 10.0)[0]
    lean = np.array([1.0, 0.0, -0.5]) / np.hypot(1.0, 0.5)
    assert np.allclose(p, np.array([50.0, 0.0, 0.0]) + 5.0 * lean, atol=0.6), p


def test_an_elliptic_cylinder_covers_only_its_heights() -> None:
    s = EllipticCylinder(50.0, 30.0, -10.0, 10.0)
    assert s.covers(np.zeros(3), np.array([-10.0, 0.0, 11.0])).tolist() == [True, True, False]
    assert s.describe() == {
        "kind": "elliptic cylinder",
        "a_mm": 50.0,
        "b_mm": 30.0,
        "z_min_mm": -10.0,
        "z_max_mm": 10.0,
    }


def test_shapes_by_parameters_are_read_and_an_ellipsoid_holds_its_bbs_along_the_normal() -> None:
    assert shape_from_text("cylinder:60,-40:40") == EllipticCylinder(60.0, 60.0, -40.0, 40.0)
    assert shape_from_text("cylinder:120,90,-70:70") == EllipticCylinder(120.0, 90.0, -70.0, 70.0)
    assert shape_from_text("ellipsoid:70,60,90") == Ellipsoid(70.0, 60.0, 90.0, -81.0, 81.0)
    s = shape_from_text("ellipsoid:70,60,90,-30:60")
    assert (s.z_min_mm, s.z_max_mm) == (-30.0, 60.0) and s.covers(np.zeros(2), np.array([-31.0, 0.0])).tolist() == [
        False,
        True,
    ]
    for bad, needle in (
        ("ellipsoid:70,60", "expected ellipsoid"),
        ("cylinder:60", "expected cylinder"),
        ("cylinder:60,x:3", "numbers"),
        ("ellipsoid:70,60,90,50:10", "the lower first"),
        ("ellipsoid:70,60,90,-100:0", "within the ellipsoid"),
        ("ellipsoid:70,nan,90", "semi-axes"),
        ("sphere:3", "expected cylinder"),
    ):
        with pytest.raises(ValueError, match=needle):
            shape_from_text(bad)
    ang, z = np.radians(np.arange(0.0, 360.0, 15.0)), np.linspace(-80.0, 80.0, 24)
    on, out = s.points(ang, z, 0.0), s.points(ang, z, D_MM)
    assert np.allclose(((on / [70.0, 60.0, 90.0]) ** 2).sum(-1), 1.0)  # on the surface
    assert np.allclose(np.linalg.norm(out - on, axis=-1), D_MM / 2)  # a BB's radius out
    normal = on / np.array([70.0, 60.0, 90.0]) ** 2
    assert np.allclose(np.cross(out - on, normal), 0.0, atol=1e-9)  # along the normal
    assert np.allclose(polar_angle(s, address_angle(s, ang, 20.0), np.full(ang.size, 20.0)), ang, atol=1e-3)
