"""The fast kernels of detection and tracking against plain reference computations written here."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from calib.detect import _binned_line_integrals, _refine, solve3
from calib.track import _median, _min_cost_assignment, match_frame


def _blob_frame(rng: np.random.Generator, centres: np.ndarray, radius: float, shape: tuple[int, int] = (96, 96)):
    """Raw counts of balls over a sloped background, with dark and flat."""
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    li = 0.2 + 0.002 * cols + 0.001 * rows
    for cx, cy in centres:
        r2 = (cols - cx) ** 2 + (rows - cy) ** 2
        li += 0.4 * np.sqrt(np.clip(1.0 - r2 / radius**2, 0.0, None))
    dark = np.full(shape, 100.0, np.float32) + rng.normal(0, 1, shape).astype(np.float32)
    flat = np.full(shape, 20000.0, np.float32)
    raw = rng.poisson((flat - dark) * np.exp(-li)) + dark
    return np.clip(raw, 0, 65535).astype(np.uint16), dark, flat


def _refine_reference(raw, dark, den, col0, row0, radius, half, passes):
    """The centroid refinement written the plain way: every pass visits the whole window."""
    cx, cy = col0, row0
    r_in2, r_w2 = (radius + 1.0) ** 2, (radius + 0.75) ** 2
    k = np.arange(-half, half + 1, dtype=float)
    for _ in range(passes):
        ic, ir = int(np.floor(cx + 0.5)), int(np.floor(cy + 0.5))
        win = np.s_[ir - half : ir + half + 1, ic - half : ic + half + 1]
        num = np.maximum(raw[win].astype(np.float32) - dark[win], np.float32(0.5))
        li = (-np.log(num / den[win])).astype(np.float64)
        yb, xb = np.meshgrid(k, k, indexing="ij")
        x, y = xb + ic - cx, yb + ir - cy
        out = x**2 + y**2 >= r_in2
        A = np.column_stack([np.ones(out.sum()), xb[out], yb[out]])
        coef = np.linalg.solve(A.T @ A, A.T @ li[out])
        w = li - (coef[0] + coef[1] * xb + coef[2] * yb)
        use = (x**2 + y**2 <= r_w2) & (w > 0)
        cx, cy = cx + (w[use] * x[use]).sum() / w[use].sum(), cy + (w[use] * y[use]).sum() / w[use].sum()
    x, y = xb + ic - cx, yb + ir - cy
    ring = x**2 + y**2 >= r_in2
    inner = x**2 + y**2 <= r_w2
    bg_rms = np.sqrt((w[ring] ** 2).sum() / ring.sum())
    return cx, cy, w[inner].max(), bg_rms


def test_refine_equals_the_plain_window_computation() -> None:
    rng = np.random.default_rng(3)
    centres = np.array([[30.3, 40.6], [61.8, 52.2], [47.5, 25.1]])
    raw, dark, flat = _blob_frame(rng, centres, 4.4)
    den = np.maximum(flat - dark, 1.0).astype(np.float32)
    half, radius = 11, 4.4
    for cx, cy in centres:
        for start in ((cx + 1.2, cy - 0.9), (cx - 0.4, cy + 1.4)):
            got = _refine(raw, dark, den, start[0], start[1], radius, half, 3)
            ref = _refine_reference(raw, dark, den, start[0], start[1], radius, half, 3)
            np.testing.assert_allclose(got[[0, 1, 2, 5]], ref, rtol=1e-6, atol=1e-6)  # float32 logs differ by an ulp
            assert np.hypot(got[0] - cx, got[1] - cy) < 0.3


def test_binned_line_integrals_equal_log_of_binned_counts() -> None:
    rng = np.random.default_rng(4)
    raw, dark, flat = _blob_frame(rng, np.array([[40.0, 40.0]]), 6.0)
    b = 3
    dark_b = dark.reshape(32, b, 32, b).mean((1, 3)).astype(np.float32)
    den_b = np.maximum(flat - dark, 1.0).reshape(32, b, 32, b).mean((1, 3)).astype(np.float32)
    ref = -np.log(np.maximum(raw.astype(np.float64).reshape(32, b, 32, b).mean((1, 3)) - dark_b, 0.5) / den_b)
    np.testing.assert_allclose(_binned_line_integrals(raw, dark_b, den_b, b), ref, rtol=1e-5, atol=1e-6)


def test_solve3_equals_lapack_and_gives_nan_for_a_singular_system() -> None:
    """The 3x3 solver the centroid refinement and the tracker use (in place of ``np.linalg``, whose bindings take
    seconds to compile): a symmetric system as LAPACK solves it; a singular one gives NaN, not an exception."""
    rng = np.random.default_rng(2)
    m = rng.normal(size=(5, 3))
    a, y = m.T @ m, rng.normal(size=3)
    np.testing.assert_allclose(solve3(a, y), np.linalg.solve(a, y), rtol=1e-10)
    rays = np.ones((3, 3))  # rank one: the rays of one direction meet nowhere in particular
    assert np.isnan(solve3(rays, y)).all() and np.isnan(solve3(np.zeros((3, 3)), y)).all()


def test_median_equals_numpy_and_gives_nan_for_nan_or_nothing() -> None:
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 4, 7, 8, 31, 64):
        values = rng.normal(size=n)
        values[: n // 3] = values[-1]  # ties
        before = values.copy()
        assert _median(values) == np.median(values)
        np.testing.assert_array_equal(values, before)
    assert np.isnan(_median(np.array([1.0, np.nan, 2.0])))
    assert np.isnan(_median(np.empty(0)))


@pytest.mark.parametrize("shape", [(1, 1), (5, 5), (4, 9), (9, 4), (12, 30)])
def test_min_cost_assignment_is_optimal(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(sum(shape))
    for _ in range(20):
        cost = rng.uniform(0.0, 10.0, shape)
        cost[rng.random(shape) < 0.3] = 1e6  # gated pairs, as the tracker passes them
        col = _min_cost_assignment(cost)
        rows = np.flatnonzero(col >= 0)
        assert len(rows) == min(shape) and len(set(col[rows])) == len(rows)
        r, c = linear_sum_assignment(cost)
        assert cost[rows, col[rows]].sum() == pytest.approx(cost[r, c].sum(), rel=1e-12)


def test_match_frame_removes_common_shift_and_affine_distortion() -> None:
    rng = np.random.default_rng(5)
    pred = rng.uniform(50, 700, (10, 2))
    A = np.array([[1.002, 0.003], [-0.002, 0.998]])
    cand = pred @ A.T + np.array([12.0, -9.0]) + rng.normal(0, 0.2, pred.shape)
    clutter = rng.uniform(0, 768, (30, 2))
    allc = np.concatenate([clutter, cand])
    pred_in = pred.copy()
    pred_in[3] = np.nan  # not expected in this frame
    idx, aligned = match_frame(pred_in, allc, search_px=25.0, gate_px=np.full(10, 2.0))
    expect = np.arange(10) + 30
    expect[3] = -1
    np.testing.assert_array_equal(idx, expect)
    assert np.nanmax(np.linalg.norm(aligned - np.where(np.isnan(pred_in), np.nan, cand), axis=1)) < 1.0


def test_match_frame_follows_a_jump_larger_than_the_spacing_of_the_bbs() -> None:
    """A whole frame jumps 30 px while its BBs lie about 20 px apart: the nearest candidate of most predictions
    is a neighbour's BB, but the shift most predictions agree on is the true one."""
    rng = np.random.default_rng(2)
    pred = np.array([[100.0 + 20.0 * i, 200.0 + (8.0 if i % 2 else 0.0)] for i in range(8)])
    cand = pred + np.array([30.0, 4.0]) + rng.normal(0, 0.3, pred.shape)
    idx, _ = match_frame(pred, cand[::-1], search_px=45.0, gate_px=np.full(8, 2.5), residual_px=8.0)
    np.testing.assert_array_equal(idx, np.arange(8)[::-1])


def _records(uv: np.ndarray, diameter_px: float) -> np.ndarray:
    """Candidate records of clean round blobs at ``uv``."""
    from calib.detect import N_FIELDS

    rec = np.zeros((len(uv), N_FIELDS))
    rec[:, :2] = uv
    rec[:, 2:7] = [20.0, 1.0, 0.5 * diameter_px, 1.0, 0.01]
    return rec


def test_touching_bbs_are_kept_when_resolved_into_two_blobs_and_dropped_when_merged() -> None:
    from calib.track import TrackingSettings, assign_to_predictions

    s = TrackingSettings(diameter_px=4.4)
    pred = np.array([[[100.0, 100.0], [105.0, 100.0], [200.0, 150.0]]])  # two BBs 5 px apart: they touch
    two = _records(np.array([[100.1, 100.0], [105.0, 100.1], [200.0, 150.0]]), 4.4)
    uv = assign_to_predictions([two], pred, s, gate_px=2.2)
    assert np.isfinite(uv).all()
    one = _records(np.array([[102.5, 100.0], [200.0, 150.0]]), 4.4)  # one blob of two: neither's centroid
    uv = assign_to_predictions([one], pred, s, gate_px=2.2)
    assert np.isnan(uv[0, :2]).all() and np.isfinite(uv[0, 2]).all()
