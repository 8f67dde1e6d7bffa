"""Anatomy-like clutter on experiment C's torso."""

from __future__ import annotations

import numpy as np
import pytest

from orbitct.phantoms import PhantomError, experiment_phantom
from orbitct.simulator import Beam, SimulatedBench


def test_the_anatomy_adds_to_the_torso_and_leaves_its_bbs_alone() -> None:
    plain = experiment_phantom("C", 3)
    body = experiment_phantom("C", 3, clutter="anatomy")
    assert [p.to_json() for p in body.primitives[: len(plain.primitives)]] == [p.to_json() for p in plain.primitives]
    assert np.array_equal(body.markers_xyz, plain.markers_xyz)
    labels = [p.label for p in body.primitives[len(plain.primitives) :]]
    for part in ("subcutaneous fat", "fat lobule 0", "aorta", "rib 11 left 0", "rib 12 marrow 8", "guide wire"):
        assert part in labels
    assert sum(label.startswith("ECG electrode") for label in labels) == 3
    extra = body.primitives[len(plain.primitives) :]
    inside = np.array([[p.contains(body.markers_xyz)] for p in extra]).reshape(len(extra), -1)
    assert not inside.any()  # no clutter where a BB is
    other = experiment_phantom("C", 4, clutter="anatomy")
    lobule = labels.index("fat lobule 0") + len(plain.primitives)
    assert not np.allclose(other.primitives[lobule].center, body.primitives[lobule].center)  # they follow the seed


def test_anatomy_is_refused_where_there_is_no_torso() -> None:
    with pytest.raises(PhantomError, match="made for experiment C's torso, not experiment A"):
        experiment_phantom("A", clutter="anatomy")
    with pytest.raises(PhantomError, match="unknown clutter 'organs'"):
        experiment_phantom("C", clutter="organs")


def test_the_ribs_and_electrodes_show_in_a_projection_at_every_energy() -> None:
    bench = SimulatedBench.with_panel(96, beam=Beam())
    plain = bench.line_integrals(experiment_phantom("C"), np.eye(3))
    body = bench.line_integrals(experiment_phantom("C", clutter="anatomy"), np.eye(3))
    top = slice(0, 40)  # ribs 11 and 12 and the electrodes sit in the upper third of the torso
    assert np.isfinite(body).all()
    assert (body[top] - plain[top]).max() > 0.5  # steel snaps and rib edges
    assert np.abs(body - plain).mean() > 0.01
