"""Shared fixtures: simulated scans of the paper's experiments, made once per test session."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def simulated_scan(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Path]:
    """Factory ``(experiment, size_px, n_frames)`` -> path of a cached simulated scan.

    The bench error profile scales its angular errors with the angular step; with 120 frames instead
    of the paper's 500-857 the steps are 4-7 times larger, so the tests scale the angular errors back to
    what a 500-frame scan has (``angle_scale = 120 / 500``). Shifts stay at 8 mm sine + 2 mm noise."""
    sim = pytest.importorskip("orbitct.simulator.scan")
    profiles = pytest.importorskip("orbitct.errorprofiles")
    root = tmp_path_factory.mktemp("calib-sims")
    made: dict[tuple[str, int, int], Path] = {}

    def make(experiment: str, size_px: int = 192, n_frames: int = 120) -> Path:
        key = (experiment, size_px, n_frames)
        if key not in made:
            path = root / f"{experiment}_{size_px}_{n_frames}.h5"
            errors = profiles.make_profile("bench", 0, angle_scale=n_frames / 500.0)
            sim.simulate_scan(experiment, out=path, n_frames=n_frames, detector_px=size_px, errors=errors)
            made[key] = path
        return made[key]

    return make


@pytest.fixture(scope="session")
def fov_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """256 px, 120 views; BB 8 sits high on the object and leaves the top of the FOV on the upward tilts."""
    import numpy as np

    from tests.helpers.calib_scans import perturbed, sawtooth, spiral_markers, write_scan

    nominal = sawtooth(120, 256)
    xyz = np.vstack([spiral_markers(7, radius=60.0, height=60.0), [[0.0, 60.0, 128.0]]])
    return write_scan(tmp_path_factory.mktemp("fov") / "fov.h5", nominal, perturbed(nominal, shift_mm=4.0), xyz)
