"""The predicted BB search: windows from the frames before, the whole frame when a BB is not found again."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calib.detect import FrameDetector, settings_for
from calib.options import CalibrationOptions
from calib.pipeline import _detect, _read_inputs, motion_px, projected_diameter_px
from calib.search import FULL_EVERY, LAG, SearchPlan
from calib.track import TrackingSettings, ball_like
from orbitct.compiletime import CompileClock
from orbitct.scanfile import ScanFile
from tests.helpers.calib_scans import perturbed, sawtooth, spiral_markers, write_scan

JOLTED = 9  # a view searched in windows (not a multiple of FULL_EVERY, after the first LAG)
JOLT_PX = 60.0


@pytest.fixture(scope="module")
def jolted_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """48 views whose panel jumps JOLT_PX sideways at view JOLTED (a knock): every BB leaves its window."""
    nominal = sawtooth(48, 256)
    truth = perturbed(nominal, shift_mm=2.0)
    vectors = truth.vectors.copy()
    u = vectors[JOLTED, 6:9]
    vectors[JOLTED, 3:6] -= JOLT_PX * u  # the panel moves by -60 px along its rows: the image moves by +60 px
    return write_scan(
        tmp_path_factory.mktemp("search") / "jolt.h5", nominal, truth.with_vectors(vectors), spiral_markers(8)
    )


def _truth_uv(path: Path) -> np.ndarray:
    with ScanFile(path) as sf:
        return sf.geometry("truth")[sf.projection_indices].project(sf.truth_markers_xyz())


def _detected(path: Path, bb_search: str) -> tuple[list[np.ndarray], float]:
    with ScanFile(path) as sf, CompileClock() as clock:
        inputs = _read_inputs(sf, path)
        cands, _, d_px = _detect(sf, inputs.proj, inputs.nominal, CalibrationOptions(bb_search=bb_search), None, clock)
    return cands, d_px


def _bbs_found(cands: list[np.ndarray], truth_uv: np.ndarray, d_px: float) -> np.ndarray:
    """Per view, how many of the true BB projections a ball-like candidate lies within 1 px of."""
    tracking = TrackingSettings(diameter_px=d_px)
    found = []
    for c, uv in zip(cands, truth_uv, strict=True):
        bbs = c[ball_like(c, tracking), :2]
        near = np.linalg.norm(uv[:, None] - bbs[None], axis=-1).min(1) < 1.0 if len(bbs) else np.zeros(len(uv), bool)
        found.append(int(near.sum()))
    return np.array(found)


def test_a_bb_that_jumps_out_of_its_window_is_found_by_searching_the_whole_frame(jolted_scan: Path) -> None:
    truth_uv = _truth_uv(jolted_scan)
    cands, d_px = _detected(jolted_scan, "predicted")
    found = _bbs_found(cands, truth_uv, d_px)
    assert found[JOLTED] == truth_uv.shape[1] and found[JOLTED - 1] == truth_uv.shape[1], found
    # the windows the jolted view was searched in first miss BBs: they were found by searching it whole
    with ScanFile(jolted_scan) as sf:
        nominal = sf.geometry("nominal")[sf.projection_indices]
        dark, flat = sf.dark_flat()
        frame = np.asarray(sf.frames[int(sf.projection_indices[JOLTED])])
    plan = SearchPlan.for_scan(d_px, motion_px(nominal), 3.0 * d_px / 3.17)  # as the pipeline plans it
    windows = plan.windows(JOLTED, cands, np.where(np.arange(len(cands)) % FULL_EVERY == 0, 0.0, np.nan))
    assert windows is not None and windows.followed.any()
    detector = FrameDetector(dark, flat, settings_for(projected_diameter_px(nominal, 3.17), dark.shape))
    in_windows = detector.candidates(frame, windows.centres, windows.reach_px)
    assert not plan.found_all(windows, in_windows)
    assert _bbs_found([in_windows], truth_uv[JOLTED : JOLTED + 1], d_px)[0] < truth_uv.shape[1]


def test_the_predicted_search_finds_the_bbs_the_whole_search_finds(jolted_scan: Path) -> None:
    truth_uv = _truth_uv(jolted_scan)
    predicted, d_px = _detected(jolted_scan, "predicted")
    whole, _ = _detected(jolted_scan, "full")
    assert (_bbs_found(predicted, truth_uv, d_px) == _bbs_found(whole, truth_uv, d_px)).all()
    tracking = TrackingSettings(diameter_px=d_px)
    for a, b in zip(predicted, whole, strict=True):  # the same centroids, to rounding: the same windows of pixels
        bbs_a, bbs_b = a[ball_like(a, tracking), :2], b[ball_like(b, tracking), :2]
        shared = np.linalg.norm(bbs_a[:, None] - bbs_b[None], axis=-1).min(1) < 0.5
        assert np.abs(bbs_a[shared][:, None] - bbs_b[None]).max(-1).min(1).max() < 1e-4


def test_windows_come_from_lag_frames_before_and_whole_frames_come_regularly() -> None:
    plan = SearchPlan.for_scan(diameter_px=6.0, motion_px=2.0, jitter_px=3.0)
    bb = np.zeros((1, 9))
    bb[0, [0, 1, 2, 3, 4, 5, 6]] = [100.0, 50.0, 20.0, 1.0, 3.0, 1.0, 0.0]  # a round blob of the BBs' size
    cands = [bb + np.array([[2.0 * n, 0, 0, 0, 0, 0, 0, 0, 0]]) for n in range(12)]
    floors = np.where(np.arange(12) % FULL_EVERY == 0, 7.5, np.nan)
    assert all(plan.windows(n, cands, floors) is None for n in range(LAG))
    assert plan.windows(8, cands, floors) is None  # every FULL_EVERY-th frame is searched whole
    w = plan.windows(9, cands, floors)
    assert w is not None
    assert w.centres[0] == pytest.approx(cands[9 - LAG][0, :2])
    assert w.reach_px[0] == pytest.approx(LAG * 2.0 + 3.0 + 6.0)
    assert w.followed[0] and w.floor == 7.5  # the floor of frame 4, the last searched whole before frame 9 - LAG
    assert plan.found_all(w, cands[9])
    assert not plan.found_all(w, cands[9] + np.array([[40.0, 0, 0, 0, 0, 0, 0, 0, 0]]))  # jumped out
    assert not plan.found_all(w, cands[9][:0])  # lost


@pytest.mark.parametrize("max_pending", [1000, 5])
def test_live_calibration_searches_as_offline_calibration_does(
    fov_scan: Path, tmp_path: Path, max_pending: int
) -> None:
    """The live worker searches each frame as the offline calibration does, and so do the frames left for after
    the scan (max_pending 5: the whole scan arrives at once): the same geometry, to the bit."""
    import shutil

    import calib
    from calib.follow import LiveSettings
    from calib.live import LiveCalibration

    path = tmp_path / "live.h5"
    shutil.copyfile(fov_scan, path)
    events: list[str] = []
    offline = calib.calibrate_scan(
        fov_scan, out=tmp_path / "offline.h5", bb_search="predicted", progress=lambda e: events.append(e.message)
    )
    searched = [m for m in events if "searched round the BBs found" in m]
    assert searched and int(searched[-1].split()[0]) > 40  # most frames were searched in windows
    with ScanFile(path) as sf:
        nominal, keys, frames = sf.geometry("nominal"), np.asarray(sf.image_key), sf.frames[:]
        diameter = sf.marker_diameter_mm
    assert diameter is not None
    live = LiveCalibration(
        path, nominal, keys, diameter, settings=LiveSettings(max_pending=max_pending), bb_search="predicted"
    )
    for i, (key, frame) in enumerate(zip(keys, frames, strict=True)):
        live.add_frame(i, int(key), frame)
    res = live.finish()
    assert (live.frames_detected_after_scan > 0) == (max_pending == 5)
    np.testing.assert_array_equal(res.geometry.vectors, offline.geometry.vectors)
