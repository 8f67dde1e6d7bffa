"""Two BBs in one blob: both centroids from a fit of two copies of the frame's own BB profile.

Views along the line through two nearby BBs see one blob of two; detection gives it one centroid, which is
neither BB's, and the assignment leaves both BBs out of such views. Line integrals of two balls add, so the
blob is modelled as the sum of two copies of the radial profile measured on the same frame's isolated BBs
(blur and size included, nothing assumed about the detector) over a background plane, and the two centres
are fitted by least squares. A split is kept only when the model explains the blob to the pixel noise and
the fit pins both centres (standard errors from its covariance); otherwise the BBs stay out of that view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.optimize
from numpy.typing import NDArray

#: radial bin of the measured BB profile, pixels
PROFILE_STEP_PX = 0.25


@dataclass(frozen=True)
class SplitSettings:
    """When a fitted pair of centroids is trusted (pixels at full resolution)."""

    diameter_px: float
    max_std_px: float = 0.15  # standard error of either fitted centre along its worst direction
    # centres closer than this share of the diameter are not told apart by the blob's shape: the profile model
    # (line integrals that add) misses how the detector blurs the transmitted intensity, and measured on
    # simulated pairs the fitted centres were off by about 0.4 px RMS there, twice a lone BB's error
    min_separation_ratio: float = 0.75
    max_misfit_ratio: float = 1.5  # RMS misfit over the blob / RMS of the pixel noise around it ...
    model_tolerance: float = 0.02  # ... or this share of the BB's peak, whichever is larger (the model's own error)
    max_shift_px: float = 2.0  # how far a fitted centre may lie from its predicted position
    amplitude_range: tuple[float, float] = (0.6, 1.6)  # each copy's amplitude relative to the measured profile

    @property
    def radius_px(self) -> float:
        return 0.5 * self.diameter_px


@dataclass(frozen=True)
class PairFit:
    """Two fitted centres ``uv`` (2, 2) as (col, row), their standard errors, and how well the model fits: the RMS
    misfit over the blob relative to the pixel noise (or the model's tolerance, when larger)."""

    uv: NDArray[np.float64]
    std_px: NDArray[np.float64]
    misfit_ratio: float
    amplitudes: NDArray[np.float64]

    def trusted(self, guess: NDArray[np.float64], s: SplitSettings) -> bool:
        """Whether the fit pins both centres near where they were predicted."""
        lo, hi = s.amplitude_range
        return bool(
            np.all(np.isfinite(self.uv))
            and np.all(self.std_px <= s.max_std_px)
            and np.linalg.norm(self.uv[0] - self.uv[1]) >= s.min_separation_ratio * s.diameter_px
            and self.misfit_ratio <= s.max_misfit_ratio
            and np.all(np.linalg.norm(self.uv - guess, axis=1) <= s.max_shift_px)
            and np.all((self.amplitudes >= lo) & (self.amplitudes <= hi))
        )


class FrameWindows:
    """Line integrals of one raw frame in small windows (``scan-file.md``: ``-log((raw - dark) / (flat - dark))``)."""

    def __init__(self, raw: NDArray[np.generic], dark: NDArray[np.float32], den: NDArray[np.float32]) -> None:
        self.raw, self.dark, self.den = raw, dark, den

    def window(self, col: float, row: float, half: int) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """Line integrals of the square of half-size ``half`` around the pixel nearest ``(col, row)``, and the
        (col, row) of every pixel in it; None where the square leaves the panel."""
        rows, cols = self.raw.shape
        ic, ir = int(np.floor(col + 0.5)), int(np.floor(row + 0.5))
        if ic - half < 0 or ir - half < 0 or ic + half >= cols or ir + half >= rows:
            return None
        sl = np.s_[ir - half : ir + half + 1, ic - half : ic + half + 1]
        num = np.maximum(self.raw[sl].astype(np.float64) - self.dark[sl], 0.5)
        li = -np.log(num / self.den[sl])
        rr, cc = np.mgrid[ir - half : ir + half + 1, ic - half : ic + half + 1]
        return li.ravel(), np.stack([cc.ravel(), rr.ravel()], axis=1).astype(np.float64)


def _plane_design(xy: NDArray[np.float64], origin: NDArray[np.float64]) -> NDArray[np.float64]:
    d = xy - origin
    return np.column_stack([np.ones(len(xy)), d[:, 0], d[:, 1]])


def radial_profile(frame: FrameWindows, centres: NDArray[np.float64], radius_px: float) -> NDArray[np.float64] | None:
    """Mean background-subtracted line integral of isolated BBs at ``centres`` (M, 2) against the distance from
    their centroid, in bins of :data:`PROFILE_STEP_PX` out to ``radius_px + 2.5`` (zero beyond); None without
    one BB wholly on the panel."""
    reach = radius_px + 2.5
    half = int(np.ceil(reach)) + 3
    edges = np.arange(0.0, reach + PROFILE_STEP_PX, PROFILE_STEP_PX)
    total = np.zeros(len(edges) - 1)
    count = np.zeros(len(edges) - 1)
    for c in centres:
        got = frame.window(c[0], c[1], half)
        if got is None:
            continue
        li, xy = got
        r = np.linalg.norm(xy - c, axis=1)
        out = r > reach
        coef, *_ = np.linalg.lstsq(_plane_design(xy[out], c), li[out], rcond=None)
        z = li - _plane_design(xy, c) @ coef
        idx = np.digitize(r[~out], edges) - 1
        np.add.at(total, idx, z[~out])
        np.add.at(count, idx, 1.0)
    if not count.any():
        return None
    mids = 0.5 * (edges[:-1] + edges[1:])
    seen = count > 0
    prof = np.interp(mids, mids[seen], total[seen] / count[seen])
    return np.stack(
        [np.concatenate([[0.0], mids, [reach + PROFILE_STEP_PX]]), np.concatenate([[prof[0]], prof, [0.0]])]
    )


def fit_pair(
    frame: FrameWindows, guess: NDArray[np.float64], profile: NDArray[np.float64], s: SplitSettings
) -> PairFit | None:
    """Least-squares fit of two copies of ``profile`` (from :func:`radial_profile`) plus a background plane to
    the blob around the predicted centres ``guess`` (2, 2); None where the window leaves the panel."""
    reach = float(profile[0, -1])
    mid = guess.mean(0)
    half = int(np.ceil(0.5 * np.linalg.norm(guess[0] - guess[1]) + reach + s.max_shift_px)) + 3
    got = frame.window(mid[0], mid[1], half)
    if got is None:
        return None
    li, xy = got
    plane = _plane_design(xy, mid)

    slope = np.gradient(profile[1], profile[0])

    def design(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Model columns (two profiles, plane), distances to both centres (M, 2), unit vectors from pixel to centre."""
        c = p.reshape(2, 2)
        d = c[None] - xy[:, None]  # (M, 2 centres, 2)
        r = np.linalg.norm(d, axis=-1)
        f = np.interp(r, profile[0], profile[1], right=0.0)
        unit = d / np.maximum(r, 1e-9)[..., None]
        return np.column_stack([f, plane]), r, unit

    def solved(
        p: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        a, r, unit = design(p)
        q, _ = np.linalg.qr(a)
        coef = np.linalg.lstsq(a, li, rcond=None)[0]  # also when the centres meet (two equal columns)
        jac = np.interp(r, profile[0], slope, right=0.0)[..., None] * unit
        return a @ coef - li, coef.astype(np.float64), q.astype(np.float64), jac

    def residual(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return solved(p)[0]

    def jacobian(p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Variable projection (Kaufman): the model's derivative along each centre coordinate, amplitudes held,
        projected off the span of the columns (the amplitudes and the plane re-fit to any change)."""
        _, coef, q, grad = solved(p)
        dA = np.concatenate([coef[0] * grad[:, 0], coef[1] * grad[:, 1]], axis=1)  # (M, 4)
        return dA - q @ (q.T @ dA)

    sol = scipy.optimize.least_squares(residual, guess.ravel(), jac=jacobian, method="lm", x_scale=0.5)
    uv = sol.x.reshape(2, 2)
    res, coef, _, _ = solved(sol.x)
    n_free = len(li) - 9
    s2 = float(res @ res) / max(n_free, 1)
    jtj = sol.jac.T @ sol.jac
    try:
        cov = s2 * np.linalg.inv(jtj)
        std = np.array([np.sqrt(np.linalg.eigvalsh(cov[2 * i : 2 * i + 2, 2 * i : 2 * i + 2]).max()) for i in range(2)])
    except np.linalg.LinAlgError:
        std = np.full(2, np.inf)
    d = np.min(np.linalg.norm(xy[:, None] - uv[None], axis=-1), axis=1)
    inside = d <= s.radius_px + 1.0
    outside = d > reach
    noise = float(np.sqrt(np.mean(res[outside] ** 2))) if outside.sum() > 10 else np.nan
    misfit = float(np.sqrt(np.mean(res[inside] ** 2))) if inside.any() else np.nan
    allowed = max(noise, s.model_tolerance * float(profile[1].max()))
    return PairFit(uv=uv, std_px=std, misfit_ratio=misfit / allowed if allowed > 0 else np.inf, amplitudes=coef[:2])


def merged_pairs(
    predicted: NDArray[np.float64], uv: NDArray[np.float64], within_px: float
) -> list[tuple[int, int, int]]:
    """``(view, j, k)`` where BBs j and k are predicted closer than ``within_px`` with no third BB near them,
    and at least one of them has no detection."""
    out = []
    for p in range(predicted.shape[0]):
        pr = predicted[p]
        vis = np.flatnonzero(np.isfinite(pr).all(1))
        if vis.size < 2:
            continue
        dd = np.linalg.norm(pr[vis, None] - pr[None, vis], axis=-1)
        np.fill_diagonal(dd, np.inf)
        for a, b in zip(*np.nonzero(np.triu(dd < within_px)), strict=True):
            if (dd[a] < 2.0 * within_px).sum() > 1 or (dd[b] < 2.0 * within_px).sum() > 1:
                continue  # a third BB close by: the blob is not a pair
            j, k = int(vis[a]), int(vis[b])
            if not (np.isfinite(uv[p, j]).all() and np.isfinite(uv[p, k]).all()):
                out.append((p, j, k))
    return out


def isolated(predicted: NDArray[np.float64], uv: NDArray[np.float64], clear_px: float) -> NDArray[np.intp]:
    """BBs of one view detected and with no other BB predicted within ``clear_px``."""
    vis = np.isfinite(predicted).all(1)
    dd = np.linalg.norm(predicted[:, None] - predicted[None], axis=-1)
    dd[~vis] = np.inf
    dd[:, ~vis] = np.inf
    np.fill_diagonal(dd, np.inf)
    return np.flatnonzero(np.isfinite(uv).all(1) & (dd.min(1, initial=np.inf) > clear_px))


__all__ = ["FrameWindows", "PairFit", "SplitSettings", "fit_pair", "isolated", "merged_pairs", "radial_profile"]
