"""Defective pixels: found from the darks and flats, filled from their row neighbours, in the scan file's line
integrals."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from orbitct.defects import DefectMap
from orbitct.scanfile import ScanFile
from orbitct.simulator import DetectorModel, simulate_scan


def _dark_flat(model: DetectorModel, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    dark = np.mean([model.dark(rng, shape) for _ in range(4)], axis=0)
    flat = np.mean([model.flat(rng, shape) for _ in range(4)], axis=0)
    return dark, flat


def test_the_dead_pixels_and_columns_of_a_panel_are_found_from_its_darks_and_flats() -> None:
    model = DetectorModel(dead_pixel_fraction=0.002, dead_columns=3)
    shape = (96, 128)
    found = np.zeros(shape, dtype=bool)
    found.ravel()[DefectMap.from_dark_flat(*_dark_flat(model, shape)).pixels] = True
    assert np.array_equal(found, model.dead(shape))


def test_a_defect_is_interpolated_from_its_row_neighbours_and_copied_at_the_edge() -> None:
    dark = np.zeros((3, 8))
    flat = np.full((3, 8), 1000.0)
    flat[:, 3] = flat[:, 4] = 0.0  # two dead columns side by side
    flat[1, 0] = 0.0  # a dead pixel at the left edge
    defects = DefectMap.from_dark_flat(dark, flat)
    assert defects.count == 3 + 3 + 1
    ramp = np.tile(np.arange(8, dtype=np.float32) * 10.0, (3, 1))
    broken = ramp.copy()
    broken[:, 3:5] = 1e6
    broken[1, 0] = -5.0
    filled = defects.filled(broken)
    assert np.allclose(filled[:, 1:], ramp[:, 1:]) and filled[1, 0] == ramp[1, 1]  # edge: the nearest good pixel
    assert broken[0, 3] == 1e6  # a copy: the frame read stays as it was
    counts = defects.filled(np.full((3, 8), 7, dtype=np.uint16))
    assert counts.dtype == np.uint16 and (counts == 7).all()
    clean = DefectMap.from_dark_flat(dark, np.full((3, 8), 1000.0))
    assert clean.count == 0 and clean.filled(broken) is broken


def test_a_scan_with_dead_columns_has_no_infinite_line_integrals(tmp_path: Path) -> None:
    model = DetectorModel(dead_columns=2)
    path = tmp_path / "dead.h5"
    simulate_scan("A", out=path, n_frames=3, detector_px=64, n_dark=2, n_flat=2, detector=model)
    with ScanFile(path) as sf:
        li = sf.line_integrals(int(sf.projection_indices[0]))
        dead = np.flatnonzero(model.dead((64, 64)).all(axis=0))
        assert sf.defects().count == 2 * 64
    assert li.max() < 5.0  # the object's thickest chord, not -log(noise / 1)
    for c in dead:  # filled between its neighbours
        lo, hi = np.minimum(li[:, c - 1], li[:, c + 1]), np.maximum(li[:, c - 1], li[:, c + 1])
        assert np.all((li[:, c] >= lo - 1e-5) & (li[:, c] <= hi + 1e-5))


def test_a_dead_row_is_filled_from_the_rows_above_and_below_and_the_rest_as_before() -> None:
    dark = np.zeros((6, 5))
    flat = np.full((6, 5), 1000.0)
    flat[2, :] = 0.0  # a whole dead row
    flat[4, 1] = 0.0  # and a dead pixel elsewhere
    defects = DefectMap.from_dark_flat(dark, flat)
    assert defects.count == 5 + 1
    ramp = np.add.outer(np.arange(6.0) * 10.0, np.arange(5.0))  # linear down the columns and along the rows
    broken = ramp.copy()
    broken[2, :] = 1e6
    broken[4, 1] = 1e6
    assert np.allclose(defects.filled(broken), ramp)
