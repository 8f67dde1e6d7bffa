"""BB identities: duplicates of one BB merge, two real BBs close together stay two."""

from __future__ import annotations

import numpy as np

from calib.identify import merge_duplicates


def _tracks(n: int, frames: list[range]) -> np.ndarray:
    uv = np.full((n, len(frames), 2), np.nan)
    for k, r in enumerate(frames):
        uv[list(r), k] = 100.0 + k
    return uv


def test_pieces_of_one_bb_never_seen_together_merge_into_the_one_seen_more() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [60.0, 0.0, 0.0]])  # 4 mm apart: a 3 mm BB placed twice
    uv = _tracks(100, [range(0, 70), range(70, 100), range(0, 100)])
    out = merge_duplicates(xyz, uv, diameter_mm=3.0)
    np.testing.assert_array_equal(out, xyz[[0, 2]])


def test_two_bbs_4_mm_apart_seen_together_stay_two() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    uv = _tracks(100, [range(0, 100), range(10, 90)])
    np.testing.assert_array_equal(merge_duplicates(xyz, uv, diameter_mm=3.0), xyz)


def test_centres_closer_than_a_bb_are_one_bb_even_if_seen_together() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    uv = _tracks(100, [range(0, 100), range(0, 40)])
    np.testing.assert_array_equal(merge_duplicates(xyz, uv, diameter_mm=3.0), xyz[[0]])
