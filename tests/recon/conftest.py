"""Shared fixtures for reconstruction tests (helpers live in ``tests.helpers.recon``)."""

from __future__ import annotations

import numpy as np
import pytest

from orbitct.geometry import Panel, ViewGeometry


@pytest.fixture
def random_geometry() -> ViewGeometry:
    """Arbitrary (perturbed, tilted, shifted, rotated-detector) views on a small detector."""
    rng = np.random.default_rng(7)
    n = 9
    det = Panel(30, 36, 1.3, 1.1)
    return ViewGeometry.from_carm(
        rng.uniform(0, 2 * np.pi, n),
        rng.uniform(-0.7, 0.7, n),
        rng.uniform(250, 320, n),
        520.0,
        det,
        du=rng.normal(0, 4, n),
        dv=rng.normal(0, 4, n),
        eta=rng.normal(0, 0.3, n),
        shift=rng.normal(0, 3, (n, 3)),
    )
