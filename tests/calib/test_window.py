"""The live calibration's sliding bundle adjustment: points triangulated through the nominal geometry carry the
orbit's errors; adjusting the latest frames' poses and those points together brings both nearer the truth."""

from __future__ import annotations

import numpy as np

from calib.model import ViewModel, ViewState
from calib.window import SlidingBundle
from orbitct.rotations import rotvec_to_matrix
from tests.helpers.calib_scans import sawtooth, spiral_markers


def test_a_window_refines_the_points_and_the_poses_it_covers() -> None:
    rng = np.random.default_rng(5)
    nominal = sawtooth(80, 256)
    model = ViewModel(nominal)
    xyz = spiral_markers(8, radius=50.0, height=50.0)
    truth = ViewState(rotvec_to_matrix(np.cumsum(rng.normal(0, 2e-3, (80, 3)), 0)),
                      np.cumsum(rng.normal(0, 0.4, (80, 3)), 0), np.zeros((80, 0)))
    uv = model.project(truth, xyz) + rng.normal(0, 0.05, (80, 8, 2))
    uv[:, 7] = np.nan  # one BB never seen: not in any window
    keys = tuple(range(100, 108))
    biased = xyz + rng.normal(0, 1.0, xyz.shape)  # points off by a millimetre, as rays through nominal views give
    window = SlidingBundle(size=40, every=20)
    start = ViewState(truth.R.copy(), truth.t + rng.normal(0, 0.5, (80, 3)), np.zeros((80, 0)))
    refined: dict[int, np.ndarray] = {}
    for p in range(80):
        window.add(p, keys, uv[p], ViewState(start.R[p : p + 1], start.t[p : p + 1], start.k[p : p + 1]))
        assert window.due == (p + 1 >= 40 and (p + 1) % 20 == 0)
        if window.due:
            refined = window.refine(nominal, {k: refined.get(k, biased[i]) for i, k in enumerate(keys)}, loss_px=0.1)
    assert window.windows == 3 and set(refined) == set(keys[:7])
    got = np.array([refined[k] for k in keys[:7]])
    # the gauge holds the points' centroid, orientation and size: compare shapes (distances between the points)
    d_true = np.linalg.norm(xyz[:7, None] - xyz[None, :7], axis=-1)
    d_got = np.linalg.norm(got[:, None] - got[None], axis=-1)
    d_biased = np.linalg.norm(biased[:7, None] - biased[None, :7], axis=-1)
    assert np.abs(d_got - d_true).max() < 0.3 * np.abs(d_biased - d_true).max()
    assert window.seconds > 0


def test_a_window_with_fewer_than_four_bbs_changes_nothing() -> None:
    nominal = sawtooth(10, 128)
    window = SlidingBundle(size=5, every=5)
    uv = np.full((3, 2), 10.0)
    for p in range(5):
        window.add(p, (1, 2, 3), uv, ViewModel(nominal[p : p + 1]).identity())
    assert window.due and window.refine(nominal, {1: np.zeros(3), 2: np.ones(3), 3: np.full(3, 2.0)}, 0.1) == {}
