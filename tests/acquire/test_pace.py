"""The pace of a step-mode scan: moves and frames learned as they run, the rest predicted from them."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest

from acquire.pace import ScanPace
from acquire.plan import plan_bench_scan
from orbitct.orbits import make_orbit
from tests.helpers.bench import small_config


def _frames() -> list:
    orbit = make_orbit("sawtooth", n_frames=24, amplitude_deg=6.0)
    return list(plan_bench_scan(small_config(), orbit.theta, orbit.phi))


def _travel(start: Mapping[str, float], end: Mapping[str, float]) -> float:
    return max(abs(end[k] - start[k]) for k in end) / 10.0  # every axis at 10 units/s


def test_nothing_is_predicted_before_a_frame_was_measured() -> None:
    assert ScanPace(_frames(), _travel, 0.05).seconds_left(0) is None


def test_the_rest_is_predicted_from_the_moves_and_frames_measured_so_far() -> None:
    frames = _frames()
    pace = ScanPace(frames, _travel, settle_s=0.05)
    offset, factor, acquire = 0.3, 1.5, {0: 0.2, 1: 0.05, 2: 0.04}  # projection, flat, dark (image keys)
    truth = []
    for k, f in enumerate(frames):
        moves = k > 0 and f.targets != frames[k - 1].targets
        move_s = offset + factor * _travel(frames[k - 1].targets, f.targets) if moves else 0.0
        truth.append(move_s + acquire[f.image_key])
    half = len(frames) // 2
    for k in range(half):
        pace.moved(k, truth[k] - acquire[frames[k].image_key])
        pace.took(k, acquire[frames[k].image_key])
    assert pace.seconds_left(half) == pytest.approx(sum(truth[half:]), rel=0.1)
    assert pace.projections_seen == sum(f.image_key == 0 for f in frames[:half])


def test_a_kind_not_yet_seen_is_taken_as_the_slowest_seen() -> None:
    frames = _frames()
    pace = ScanPace(frames, _travel, settle_s=0.0)
    first_projection = next(k for k, f in enumerate(frames) if f.image_key == 0)
    for k in range(first_projection):  # darks and flats only
        pace.took(k, 0.1)
    left = pace.seconds_left(first_projection)
    assert left is not None and left >= 0.1 * (len(frames) - first_projection)


def test_with_no_move_measured_a_move_takes_its_travel_and_the_settling() -> None:
    frames = _frames()
    pace = ScanPace(frames, _travel, settle_s=0.05)
    pace.took(0, 0.0)
    travel = [_travel(frames[k - 1].targets, frames[k].targets) for k in range(1, len(frames))]
    moves = [t for k, t in enumerate(travel, start=1) if frames[k].targets != frames[k - 1].targets]
    assert pace.seconds_left(1) == pytest.approx(np.sum(np.asarray(moves) + 0.05))


def test_moves_of_different_lengths_fit_the_offset_and_the_factor() -> None:
    steps_deg = [0.0, 5.0, 10.0, 20.0, 5.0, 40.0, 2.0, 15.0, 30.0]
    theta = np.radians(np.cumsum(steps_deg))
    frames = list(plan_bench_scan(small_config(), theta, np.zeros_like(theta)))
    pace = ScanPace(frames, _travel, settle_s=0.05)
    moves = [k for k in range(1, len(frames)) if frames[k].targets != frames[k - 1].targets]
    travel = {k: _travel(frames[k - 1].targets, frames[k].targets) for k in moves}
    for k in moves:
        pace.moved(k, 0.3 + 1.5 * travel[k])
    offset, factor = pace.move_model()
    assert offset == pytest.approx(0.3, rel=0.15) and factor == pytest.approx(1.5, rel=0.15)
