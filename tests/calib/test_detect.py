"""Detection on synthetic frames rendered here (exact sphere line integrals, Poisson noise)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calib.detect import FrameDetector, settings_for
from calib.options import CalibrationOptions
from calib.pipeline import _estimate_diameter_mm
from orbitct.scanfile import ScanFile
from tests.helpers.calib_scans import (
    SAD,
    SDD,
    perturbed,
    sawtooth,
    spiral_markers,
    write_scan,
)


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    nominal = sawtooth(6, 256)
    return write_scan(
        tmp_path_factory.mktemp("det") / "s.h5", nominal, perturbed(nominal), spiral_markers(8), diameter_attr=False
    )


def _errors(path: Path) -> tuple[np.ndarray, np.ndarray, int]:
    with ScanFile(path) as sf:
        dark, flat = sf.dark_flat()
        d_px = 3.17 * SDD / SAD / sf.panel.pitch_col
        det = FrameDetector(dark, flat, settings_for(d_px, sf.panel.shape))
        truth = sf.geometry("truth").project(sf.truth_markers_xyz())
        ours, paper, missed = [], [], 0
        for i in sf.projection_indices:
            c = det.candidates(np.asarray(sf.frames[i]))
            d = np.linalg.norm(c[:, None, :2] - truth[i][None], axis=-1)
            j = d.argmin(0)
            hit = d[j, np.arange(truth.shape[1])] < 1.5
            missed += int((~hit).sum())
            ours.append((c[j, 0:2] - truth[i])[hit])
            paper.append((c[j, 7:9] - truth[i])[hit])
    return np.concatenate(ours), np.concatenate(paper), missed


def test_every_bb_found_with_subpixel_centroids(small_scan: Path) -> None:
    ours, paper, missed = _errors(small_scan)
    assert missed == 0
    rms = np.sqrt((ours**2).sum(1).mean())
    assert rms < 0.12
    # the paper's plain ROI centroid (no background removal) is measurably worse
    assert np.sqrt((paper**2).sum(1).mean()) > 3 * rms


def test_bb_diameter_estimated_when_the_file_does_not_say(small_scan: Path) -> None:
    with ScanFile(small_scan) as sf:
        assert sf.marker_diameter_mm is None
        dark, flat = sf.dark_flat()
        nominal = sf.geometry("nominal")[sf.projection_indices]
        mag = float(np.median(nominal.sdd / nominal.sod()))
        d = _estimate_diameter_mm(sf, sf.projection_indices, dark, flat, mag, sf.panel.pitch_col, CalibrationOptions())
    assert d == pytest.approx(3.17, rel=0.25)


def test_a_frame_full_of_stronger_structure_keeps_its_bbs_among_the_candidates() -> None:
    """A lateral view of a torso holds more peaks stronger than its BBs (bone edges, screws) than a fixed 128
    candidates: the detector keeps the strongest per area searched (one per CANDIDATE_AREA_PX binned pixels)."""
    from calib.detect import CANDIDATE_AREA_PX

    rng = np.random.default_rng(3)
    size, d_px = 512, 3.6
    cells = rng.permutation([(r, c) for r in range(20) for c in range(20)])
    centres = cells * 25.0 + 18.0 + rng.uniform(-3, 3, cells.shape)
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    li = np.zeros((size, size))
    for k, (r, c) in enumerate(centres[:230]):
        radius, height = (1.8, 0.8) if k < 10 else (5.0, 2.5)  # the first ten are the BBs: smaller, fainter
        rho2 = np.clip(radius**2 - (rows - r) ** 2 - (cols - c) ** 2, 0.0, None)
        li += height * np.sqrt(rho2) / radius
    dark = np.full((size, size), 100.0, np.float32)
    flat = np.full((size, size), 20000.0, np.float32)
    raw = rng.poisson((flat - dark) * np.exp(-li)) + dark
    det = FrameDetector(dark, flat, settings_for(d_px, (size, size)))
    assert det.settings.max_candidates == 128 and size * size // CANDIDATE_AREA_PX == 256
    c = det.candidates(raw)
    assert len(c) > 128
    found = np.linalg.norm(c[:, None, :2] - centres[None, :10, ::-1], axis=-1).min(0)
    assert (found < 1.0).all(), found


def test_dead_columns_are_filled_so_they_neither_hide_bbs_nor_pass_for_them() -> None:
    """A column that reads its dark offset normalises to noise where the object's line integral should be: a BB it
    crosses is measured off its centre (0.14 px here) unless the column is filled from its neighbours."""
    rng = np.random.default_rng(5)
    size, d_px = 256, 6.0
    centres = np.array([[60.0, 80.0], [128.0, 130.4], [190.0, 40.0], [200.0, 210.0]])  # (row, col)
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    li = np.full((size, size), 2.0)  # behind the object
    for r, c in centres:
        rho2 = np.clip((d_px / 2) ** 2 - (rows - r) ** 2 - (cols - c) ** 2, 0.0, None)
        li += 0.8 * np.sqrt(rho2) / (d_px / 2)
    dark = np.full((size, size), 100.0)
    flat = np.full((size, size), 20000.0)
    dead = [130, 20]  # one through the second BB, one in the open
    flat[:, dead] = dark[:, dead]
    raw = (rng.poisson((flat - dark) * np.exp(-li)) + dark).astype(np.uint16)
    raw[:, dead] = np.rint(100 + 3.0 * rng.standard_normal((size, 2)))  # the dark offset and its read noise
    det = FrameDetector(dark.astype(np.float32), flat.astype(np.float32), settings_for(d_px, (size, size)))
    assert det.defects.count == 2 * size
    c = det.candidates(raw)
    off = np.linalg.norm(c[:, None, :2] - centres[None, :, ::-1], axis=-1)
    assert (off.min(0) < 0.08).all(), off.min(0)  # every BB, the one on the dead column too
    assert (off.min(1) < 2.0).sum() == 4 and len(c[c[:, 2] > 50]) == 4  # and nothing strong along the columns


def test_detection_spread_is_each_detections_background_rms_over_the_typical_one() -> None:
    from calib.detect import CANDIDATE_FIELDS, SPREAD_RANGE, detection_spread

    def records(cols_rows_rms: list[tuple[float, float, float]]) -> np.ndarray:
        rec = np.zeros((len(cols_rows_rms), len(CANDIDATE_FIELDS)))
        for i, (c, r, rms) in enumerate(cols_rows_rms):
            rec[i, 0], rec[i, 1], rec[i, CANDIDATE_FIELDS.index("background_rms")] = c, r, rms
        return rec

    cands = [
        records([(10.5, 20.25, 0.1), (40.0, 41.0, 0.3), (70.0, 7.0, 9.0)]),
        records([(11.0, 21.0, 0.1), (41.0, 42.0, 0.01)]),
        records([]),
    ]
    uv = np.array(
        [
            [[10.5, 20.25], [40.0, 41.0], [70.0, 7.0]],
            [[11.0, 21.0], [41.0, 42.0], [np.nan, np.nan]],
            [[12.0, 22.0], [np.nan, np.nan], [50.0, 50.0]],
        ]
    )
    spread = detection_spread(cands, uv)
    typical = 0.1  # the median of the five detections found: 0.01, 0.1, 0.1, 0.3, 9.0
    assert spread[0, 0] == pytest.approx(1.0) and spread[0, 1] == pytest.approx(0.3 / typical)
    assert spread[0, 2] == SPREAD_RANGE[1] and spread[1, 1] == SPREAD_RANGE[0]  # bounded both ways
    # a position no candidate has (a blob split in two) and frames without candidates count as typical
    assert spread[2, 0] == 1.0 and spread[2, 2] == 1.0


def test_the_threshold_follows_the_panels_noise_correlation() -> None:
    """On an indirect panel each quantum's light spreads over its neighbours, so their noise is correlated: the
    neighbour differences the threshold is estimated from understate it, and a bare object let about fifty noise
    peaks pass. Two single flats measure the correlation; with it, noise alone passes nothing."""
    from orbitct.simulator import DetectorModel

    shape, d_px = (192, 192), 4.0
    li = np.full(shape, 1.5, np.float32)  # behind the object, nothing in it
    for noise_blur, correlated in ((0.0, False), (0.6, True)):
        model = DetectorModel(blur_sigma_px=1.0, noise_blur_px=noise_blur)
        rng = np.random.default_rng(1)
        darks = [model.dark(rng, shape).astype(np.float32) for _ in range(4)]
        flats = [model.flat(rng, shape) for _ in range(4)]
        dark = np.mean(darks, axis=0)
        flat = np.mean([f.astype(np.float32) for f in flats], axis=0)
        frame = model.expose(li, rng)
        det = FrameDetector(dark, flat, settings_for(d_px, shape))
        before = len(det.candidates(frame))
        det = FrameDetector(dark, flat, settings_for(d_px, shape))
        factor = det.measure_noise_correlation(flats[0], flats[1])
        after = len(det.candidates(frame))
        if correlated:
            assert factor > 1.5 and det.noise_factor == factor
            assert before > 30 and after == 0, (before, after)
        else:
            assert abs(factor - 1.0) < 0.05 and det.noise_factor == 1.0 and after == before
