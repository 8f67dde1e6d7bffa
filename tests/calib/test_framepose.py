"""Per-frame poses while the scan runs, and the jump that says the object moved."""

from __future__ import annotations

import numpy as np
import pytest

from calib.framepose import StepWatch, fit_frame_pose
from orbitct.rotations import rot_xyz
from tests.helpers.calib_scans import sawtooth, spiral_markers


def _series(n: int, noise_mm: float, step_mm: float = 0.0, at: int = 10**9, seed: int = 0) -> np.ndarray:
    """Per-frame corrections like the bench profile: a slow sine on every component, uniform noise, a jump."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 2 * np.pi, n)
    v = 8.0 * np.sin(s[:, None] + np.arange(6)) + rng.uniform(-noise_mm, noise_mm, (n, 6))
    v[at:, 0] += step_mm
    return v


def _first_step(values: np.ndarray) -> tuple[int, int] | None:
    watch = StepWatch()
    for f, v in enumerate(values):
        step = watch.add(f, v)
        if step is not None:
            return f, step.since_frame
    return None


@pytest.mark.parametrize("seed", range(5))
def test_smooth_errors_and_frame_noise_raise_nothing(seed: int) -> None:
    assert _first_step(_series(500, noise_mm=2.0, seed=seed)) is None
    assert _first_step(_series(500, noise_mm=0.05, seed=seed)) is None


def test_a_2_mm_move_on_a_steady_bench_is_seen_within_a_few_frames() -> None:
    got = _first_step(_series(500, noise_mm=0.05, step_mm=2.0, at=250))
    assert got is not None
    raised, since = got
    assert since == 250 and raised <= 254


def test_a_move_hidden_in_large_frame_noise_takes_more_frames() -> None:
    got = _first_step(_series(500, noise_mm=2.0, step_mm=6.0, at=250))
    assert got is not None
    raised, since = got
    assert 245 <= since <= 260 and raised <= 270


def test_the_pose_of_one_frame_is_refitted_to_its_bbs_with_its_predicted_error() -> None:
    nominal = sawtooth(10, 256)[3:4]
    xyz = spiral_markers(8)
    truth = nominal.transformed(
        rot_xyz(np.array([0.01]), np.array([-0.005]), np.array([0.008])), np.array([[2.0, -1.5, 3.0]])
    )
    rng = np.random.default_rng(0)
    uv = truth.project(xyz)[0] + rng.normal(0.0, 0.1, (8, 2))
    uv[2] = np.nan  # one BB not seen
    pose = fit_frame_pose(nominal, xyz, uv, noise_px=0.1)
    assert pose is not None and pose.n_bbs == 7
    from calib.model import ViewModel

    err = np.linalg.norm(ViewModel(nominal).project(pose.state, xyz)[0] - truth.project(xyz)[0], axis=-1)
    assert err.max() < 0.3
    assert 0.02 < pose.predicted_px < 0.3 and 0.05 < pose.misfit_px < 0.2 and pose.rpe_mm < 0.2
    assert fit_frame_pose(nominal, xyz, np.where(np.arange(8)[:, None] < 3, uv, np.nan), noise_px=0.1) is None


def test_a_curve_is_not_extrapolated_across_frames_without_a_pose() -> None:
    v = _series(500, noise_mm=0.05)
    watch = StepWatch()
    for f in [*range(120), *range(210, 300)]:  # 90 frames where too few BBs were followed for a pose
        assert watch.add(f, v[f]) is None, f


def test_the_motion_watched_does_not_jump_when_a_bb_is_hidden() -> None:
    """The isocenter's shift, not the BBs' mean: hiding one BB moves the measured motion by no more than the pose's
    noise (the BBs' mean projection would move by how much that BB differs from the others)."""
    nominal = sawtooth(10, 256)[3:4]
    xyz = spiral_markers(8)
    truth = nominal.transformed(
        rot_xyz(np.array([0.02]), np.array([-0.01]), np.array([0.015])), np.array([[4.0, -3.0, 2.0]])
    )
    uv = truth.project(xyz)[0]
    every = fit_frame_pose(nominal, xyz, uv, noise_px=0.1)
    for hidden in range(8):
        one_less = fit_frame_pose(nominal, xyz, np.where(np.arange(8)[:, None] == hidden, np.nan, uv), noise_px=0.1)
        assert every is not None and one_less is not None
        assert np.abs(one_less.motion_mm - every.motion_mm).max() < 0.01, hidden


def test_one_wrong_pose_in_the_baseline_does_not_bend_the_curve() -> None:
    """A frame posed wrongly (8 mm off) among the baseline is left out of the curve; the frames after it raise
    nothing, and a real move after it is still seen at once."""
    v = _series(500, noise_mm=0.05)
    v[250] += 8.0
    assert _first_step(v) is None
    v[300:, 0] += 2.0
    got = _first_step(v)
    assert got is not None and got[1] == 300 and got[0] <= 304
