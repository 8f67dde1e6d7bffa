"""The polychromatic beam: spectrum, energy curves, beam hardening in the simulator's line integrals."""

from __future__ import annotations

import numpy as np
import pytest

from orbitct.phantoms import Phantom, Primitive, cylinder, experiment_phantom
from orbitct.phantoms.materials import mu_of
from orbitct.simulator import Beam, SimulatedBench, line_integrals

Z = (0.0, 0.0, 1.0)


def test_the_spectrum_is_a_distribution_below_the_tube_voltage_that_hardens_with_kv_and_filtration() -> None:
    e, w = Beam().spectrum()
    assert np.isclose(w.sum(), 1.0) and (w > 0).all() and e.max() < 90.0 and e.min() > 5.0
    assert 45.0 < Beam().mean_kev() < 65.0  # a filtered 90 kV beam behind a CsI panel
    assert Beam(kv=70).mean_kev() < Beam().mean_kev() < Beam(kv=120).mean_kev()
    assert Beam(filter_cu_mm=0.0).mean_kev() < Beam().mean_kev() < Beam(filter_cu_mm=0.3).mean_kev()
    assert Beam().at_kv(109.6).kv == 110.0 and Beam().at_kv(500).kv == 150.0
    assert Beam.preset("mono") is None and Beam.preset("polychromatic") == Beam()
    with pytest.raises(ValueError, match="unknown beam 'white'"):
        Beam.preset("white")


def test_thicker_material_attenuates_less_per_mm_and_metal_hardens_the_most() -> None:
    beam = Beam()
    thick = np.array([[1.0, 50.0, 300.0]], np.float32)
    water = beam.harden({("water", ""): mu_of("water") * thick}) / (mu_of("water") * thick)
    steel_mm = np.array([[0.1, 1.0, 3.0]], np.float32)
    steel = beam.harden({("steel", ""): mu_of("steel") * steel_mm}) / (mu_of("steel") * steel_mm)
    assert (np.diff(water) < 0).all() and (np.diff(steel) < 0).all()  # the beam hardens as it goes
    assert water[0, 0] > 1.0  # a thin layer sees the spectrum's softer mean (below 60 keV)
    assert steel[0, 0] / steel[0, -1] > 1.3 > water[0, 0] / water[0, -1]
    assert beam.harden({("water", ""): np.zeros((2, 2), np.float32)}).max() == 0.0  # open field stays 0


def test_each_material_is_projected_at_its_own_energies() -> None:
    """A single material's image is the hardening of its monochromatic image; an air cavity in acrylic removes
    acrylic at every energy, so the ray through both walls reads as the walls alone."""
    bench = SimulatedBench.with_panel(64)
    shell = Phantom(
        "shell",
        (
            cylinder((0, 0, 0), Z, 50.0, 100.0, material="acrylic"),
            cylinder((0, 0, 0), Z, 30.0, 100.1, material="air", displaces="acrylic"),
        ),
    )
    beam = Beam()
    mono = line_integrals(shell, bench.lab_view, 0)
    poly = line_integrals(shell, bench.lab_view, 0, beam=beam)
    rows, cols = mono.shape
    centre = mono[rows // 2, cols // 2]
    assert np.isclose(centre, mu_of("acrylic") * 40.0, rtol=1e-2)  # two 20 mm walls (near the centre)
    e, w = beam.spectrum()
    expected = -np.log(w @ np.exp(-beam.ratios((("acrylic", ""),))[0] * centre))
    assert np.isclose(poly[rows // 2, cols // 2], expected, rtol=1e-4)
    solid = Phantom("solid", (cylinder((0, 0, 0), Z, 50.0, 100.0, material="acrylic"),))
    li = line_integrals(solid, bench.lab_view, 0)
    assert np.allclose(line_integrals(solid, bench.lab_view, 0, beam=beam), beam.harden({("acrylic", ""): li}))


def test_a_primitive_without_a_known_material_is_refused_in_one_sentence() -> None:
    p = Phantom("x", (Primitive("ellipsoid", (0, 0, 0), (10, 10, 10), np.eye(3), 0.02),))
    with pytest.raises(ValueError, match="needs each primitive's material; '' is not one of"):
        line_integrals(p, SimulatedBench.with_panel(32).lab_view, 0, beam=Beam())


def test_displaces_is_kept_in_the_phantom_json_and_older_json_still_reads() -> None:
    c = experiment_phantom("C")
    back = Phantom.from_json(c.to_json())
    assert [p.displaces for p in back.primitives] == [p.displaces for p in c.primitives]
    assert {p.displaces for p in c.primitives} >= {"tissue", "trabecular", "cortical"}
    old = c.primitives[1].to_json()
    del old["displaces"]
    assert Primitive.from_json(old).displaces == ""
    assert ("titanium", "trabecular") in c.by_material and ("steel", "") in c.by_material


def test_a_higher_kv_sees_less_contrast_and_the_bench_records_its_beam() -> None:
    phantom = experiment_phantom("C")
    low = SimulatedBench.with_panel(48, beam=Beam().at_kv(70))
    high = SimulatedBench.with_panel(48, beam=Beam().at_kv(120))
    R = np.eye(3)
    assert low.line_integrals(phantom, R).max() > 1.1 * high.line_integrals(phantom, R).max()
    assert SimulatedBench().config()["beam"] == "mono" and low.config()["beam"]["kv"] == 70.0
