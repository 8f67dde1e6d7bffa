"""BB identities: duplicates of one BB merge, two real BBs close together stay two."""

from __future__ import annotations

import numpy as np

from calib.identify import merge_duplicates, twin_constellation


def _tracks(n: int, frames: list[range]) -> np.ndarray:
    uv = np.full((n, len(frames), 2), np.nan)
    for k, r in enumerate(frames):
        uv[list(r), k] = 100.0 + k
    return uv


def test_pieces_of_one_bb_never_seen_together_merge_into_the_one_seen_more() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [60.0, 0.0, 0.0]])  # 4 mm apart: a 3 mm BB placed twice
    uv = _tracks(100, [range(70), range(70, 100), range(100)])
    out = merge_duplicates(xyz, uv, diameter_mm=3.0)
    np.testing.assert_array_equal(out, xyz[[0, 2]])


def test_a_constellation_identified_twice_in_two_halves_of_the_orbit_is_found_as_pairs() -> None:
    """Eight BBs seen in frames 0-119, and the same eight moved by a similarity (as a second half that calibrated
    in a frame of its own) seen in frames 120-199, one of them also once in the first half: eight pairs. Two BBs
    that no similarity maps, and BBs at random seen in different halves, make none."""
    rng = np.random.default_rng(4)
    xyz = rng.uniform(-80.0, 80.0, (8, 3))
    angle = np.radians(2.0)
    rot = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    twin = 0.97 * xyz @ rot.T + [9.0, -14.0, 10.0]
    extra = rng.uniform(-80.0, 80.0, (2, 3))
    points = np.concatenate([xyz, twin, extra])
    uv = _tracks(200, [range(120)] * 8 + [range(120, 200)] * 8 + [range(200)] * 2)
    uv[50, 9] = 7.0  # one blob of the first half taken for a BB of the second
    pairs = twin_constellation(points, uv)
    assert sorted(pairs) == [(k, k + 8) for k in range(8)]
    others = rng.uniform(-80.0, 80.0, (18, 3))
    assert twin_constellation(others, uv) == []


def test_two_bbs_4_mm_apart_seen_together_stay_two() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    uv = _tracks(100, [range(100), range(10, 90)])
    np.testing.assert_array_equal(merge_duplicates(xyz, uv, diameter_mm=3.0), xyz)


def test_centres_closer_than_a_bb_are_one_bb_even_if_seen_together() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    uv = _tracks(100, [range(100), range(40)])
    np.testing.assert_array_equal(merge_duplicates(xyz, uv, diameter_mm=3.0), xyz[[0]])


def _records(uv: np.ndarray, radius_px: float, background_rms: float) -> np.ndarray:
    """Candidate records at pixels ``uv`` (M, 2) with a BB-like amplitude and shape."""
    from calib.detect import CANDIDATE_FIELDS

    rec = np.zeros((len(uv), len(CANDIDATE_FIELDS)))
    rec[:, 0:2] = uv
    f = CANDIDATE_FIELDS.index
    rec[:, f("score")], rec[:, f("amplitude")], rec[:, f("radius_px")] = 30.0, 1.3, radius_px
    rec[:, f("elongation")], rec[:, f("background_rms")] = 1.05, background_rms
    return rec


def test_a_bb_whose_track_broke_into_pieces_is_found_again_through_the_calibrated_views() -> None:
    """Identification kept five BBs; the sixth left only a 6-frame piece of track. Grown along its path through the
    calibrated views it is found in every frame and returned; a blob track seen in a third of the frames, and a
    round blob twice a BB's size in every frame (a screw head), are not BBs."""
    from calib.identify import recover_missed
    from calib.track import TrackingSettings
    from tests.helpers.calib_scans import sawtooth, spiral_markers

    g = sawtooth(60, 256)
    xyz = spiral_markers(6)
    clutter = np.array([[10.0, -20.0, 5.0], [-30.0, 15.0, -20.0]])
    uv, uc = g.project(xyz), g.project(clutter)
    rng = np.random.default_rng(0)
    cands = []
    for p in range(g.n_views):
        rec = [_records(uv[p] + rng.normal(0, 0.05, uv[p].shape), 2.0, 0.05)]
        if p % 3 == 0:
            rec.append(_records(uc[p, :1], 2.0, 0.05))
        rec.append(_records(uc[p, 1:], 4.0, 0.05))
        cands.append(np.concatenate(rec))
    frags = np.full((g.n_views, 3, 2), np.nan)
    frags[20:26, 0] = uv[20:26, 5]
    frags[0:12:3, 1] = uc[0:12:3, 0]
    frags[30:40, 2] = uc[30:40, 1]
    settings = TrackingSettings(diameter_px=4.0)
    found = recover_missed(cands, g, xyz[:5], frags, settings, min_observations=10, diameter_mm=3.17)
    assert found.shape == (1, 3)
    np.testing.assert_allclose(found[0], xyz[5], atol=0.2)
    assert recover_missed(cands, g, xyz, frags, settings, min_observations=10, diameter_mm=3.17).shape == (0, 3)


def test_a_blob_is_like_the_bbs_when_its_size_and_background_are() -> None:
    """The rule that keeps a structure of the object, round for a few frames, from being taken for a BB (by the
    search for lost BBs and by live following): median radius within 20 % of the BBs', background at most 2.5
    times as rough. The numbers are those of a 256 px experiment A scan, where a structure followed for 18 frames
    had a radius 1.23 times the BBs'."""
    from calib.detect import N_FIELDS
    from calib.track import BG_RMS, RADIUS, like_the_others

    def blobs(radius: float, rough: float, n: int = 12) -> np.ndarray:
        r = np.full((n, N_FIELDS), np.nan)
        r[:, RADIUS] = radius + np.linspace(-0.05, 0.05, n)
        r[:, BG_RMS] = rough
        return r

    bbs = np.concatenate([blobs(1.88, 0.14), blobs(1.85, 0.13)])
    assert like_the_others(blobs(1.95, 0.15), bbs)
    assert not like_the_others(blobs(2.31, 0.18), bbs)  # the structure
    assert not like_the_others(blobs(1.9, 0.40), bbs)  # a BB-sized blob on a bone edge


def test_a_view_that_jumped_farther_than_its_bbs_lie_apart_is_placed_on_its_own_blobs() -> None:
    """Eight BBs; every view's true pose is its guess moved 30-40 mm and turned 6 degrees (frames of an orbit eight
    times the bench profile's errors jump so), so the guess puts no BB on its own blob. Placed by the 2-D
    similarity that carries the most BBs onto blobs and a pose fitted to them, every BB lands within 0.1 px of its
    blob; among clutter too. A view with three blobs keeps its guess."""
    from calib.identify import placed_by_similarity
    from calib.model import ViewModel, ViewState
    from calib.track import TrackingSettings
    from orbitct.rotations import rotvec_to_matrix
    from tests.helpers.calib_scans import sawtooth, spiral_markers

    g = sawtooth(12, 256)
    xyz = spiral_markers(8)
    model = ViewModel(g)
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(g.n_views, 3))
    rot = rotvec_to_matrix(np.radians(6.0) * axes / np.linalg.norm(axes, axis=1, keepdims=True))
    shift = rng.uniform(30.0, 40.0, (g.n_views, 1)) * rng.choice([-1.0, 1.0], (g.n_views, 3)) / np.sqrt(3)
    true = ViewState(rot, shift, np.zeros((g.n_views, 0)))
    uv = model.project(true, xyz)
    guess = model.identity()
    assert np.linalg.norm(model.project(guess, xyz) - uv, axis=-1).min() > 8.0  # no BB near its own blob
    clutter = rng.uniform(20.0, 236.0, (g.n_views, 6, 2))
    cands = [_records(np.concatenate([uv[p], clutter[p]]), 2.0, 0.05) for p in range(g.n_views)]
    cands[5] = _records(uv[5, :3], 2.0, 0.05)  # three blobs: too few to place the view
    placed = placed_by_similarity(cands, model, [guess], xyz, TrackingSettings(diameter_px=4.0), np.arange(12))
    err = np.linalg.norm(model.project(placed, xyz) - uv, axis=-1)
    others = np.arange(12) != 5
    assert err[others].max() < 0.1
    np.testing.assert_array_equal(placed.R[5], guess.R[5])
