"""From per-frame candidates to marker centroids ``(P, K, 2)`` with one identity per BB (see ``track.py``)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calib.bundle import bundle_adjust
from calib.model import ViewModel, ViewState
from calib.rays import marker_rays, triangulate_least_squares
from calib.track import TrackingSettings, assign_to_predictions, link_fragments
from orbitct.geometry import ViewGeometry


def usable_views(uv: NDArray[np.float64], min_bbs: int) -> NDArray[np.bool_]:
    """Views that see at least ``min_bbs`` markers."""
    return np.isfinite(uv).all(-1).sum(1) >= min_bbs


def fill_states(state: ViewState, solved: NDArray[np.bool_], n: int) -> ViewState:
    """States for all ``n`` views: solved ones as given, others copied from the nearest solved view."""
    idx = np.flatnonzero(solved)
    nearest = idx[np.clip(np.searchsorted(idx, np.arange(n)), 0, len(idx) - 1)]
    left = idx[np.clip(np.searchsorted(idx, np.arange(n)) - 1, 0, len(idx) - 1)]
    nearest = np.where(np.abs(left - np.arange(n)) < np.abs(nearest - np.arange(n)), left, nearest)
    return ViewState(state.R[nearest], state.t[nearest], state.k[nearest])


def rough_solve(
    model: ViewModel, uv: NDArray[np.float64], min_bbs: int = 3, iterations: int = 15
) -> tuple[ViewState, NDArray[np.float64], NDArray[np.bool_]]:
    """Quick robust bundle adjustment on the views that see enough markers; states for every view."""
    ok_views = usable_views(uv, min_bbs)
    sub = ViewModel(model.nominal[np.flatnonzero(ok_views)], "fixed")
    uvs = uv[ok_views]
    xyz0 = triangulate_least_squares(*marker_rays(sub.nominal, uvs))
    res = bundle_adjust(sub, uvs, xyz0, loss_scale_px=2.0, max_iterations=iterations)
    full = ViewState.identity(model.nominal.n_views, 0)
    full.R[ok_views], full.t[ok_views] = res.state.R, res.state.t
    return fill_states(full, ok_views, model.nominal.n_views), res.xyz, ok_views


def _fit_rms(geometry: ViewGeometry, uv: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Triangulated points ``(K,3)`` of tracks ``(N,K,2)`` and their RMS reprojection error (px)."""
    xyz = triangulate_least_squares(*marker_rays(geometry, uv))
    err = np.linalg.norm(geometry.project(xyz) - uv, axis=-1)
    seen = np.isfinite(err)
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(np.where(seen, err**2, 0.0).sum(0) / seen.sum(0))
    return xyz, rms


def merge_fragments(
    frags: NDArray[np.float64], geometry: ViewGeometry, xyz: NDArray[np.float64], tol_px: float, near_mm: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Join fragments that never share a frame, lie within ``near_mm`` of each other (rough centres ``xyz``)
    and fit one 3-D point together within ``tol_px`` RMS (greedy, best pair first).
    Returns the merged tracks and their RMS reprojection error through ``geometry``."""
    tracks = [frags[:, f] for f in range(frags.shape[1])]
    centres = [c for c in xyz]
    while True:
        stack = np.stack(tracks, 1)
        seen = np.isfinite(stack[..., 0]).T  # (F, N)
        C = np.array(centres)
        shared = seen.astype(np.int32) @ seen.T.astype(np.int32)
        near = np.linalg.norm(C[:, None] - C[None], axis=-1) < near_mm
        ia, ib = np.nonzero(np.triu((shared == 0) & near, 1))
        if ia.size == 0:
            break
        union = np.where(seen[ia].T[..., None], stack[:, ia], stack[:, ib])  # (N, pairs, 2)
        xyz_u, rms_u = _fit_rms(geometry, union)
        ok = np.isfinite(rms_u) & (rms_u < tol_px)
        if not ok.any():
            break
        best = int(np.flatnonzero(ok)[np.argmin(rms_u[ok])])
        a, b = int(ia[best]), int(ib[best])
        tracks[a], centres[a] = union[:, best], xyz_u[best]
        del tracks[b], centres[b]
    stack = np.stack(tracks, 1)
    return stack, _fit_rms(geometry, stack)[1]


def _merge_close(xyz: NDArray[np.float64], uv: NDArray[np.float64], diameter_mm: float) -> NDArray[np.float64]:
    """Centres closer than most of a BB diameter are one BB (two balls cannot overlap): average them."""
    count = np.isfinite(uv).all(-1).sum(0).astype(float)
    pts = list(xyz)
    wts = list(count)
    while len(pts) > 1:
        P = np.array(pts)
        d = np.linalg.norm(P[:, None] - P[None], axis=-1) + np.eye(len(P)) * 1e9
        a, b = np.unravel_index(np.argmin(d), d.shape)
        if d[a, b] >= 0.75 * diameter_mm:
            break
        pts[a] = (wts[a] * P[a] + wts[b] * P[b]) / (wts[a] + wts[b])
        wts[a] += wts[b]
        del pts[b], wts[b]
    return np.array(pts).reshape(-1, 3)


def identify(
    cands: list[NDArray[np.float64]],
    nominal_model: ViewModel,
    settings: TrackingSettings,
    diameter_mm: float,
    min_observations: int,
    min_found_share: float = 0.25,
    max_rough_points: int = 40,
) -> tuple[NDArray[np.float64], list[str]]:
    """Marker centroids ``(P, K, 2)`` over projection views, K found here; and warnings."""
    warnings: list[str] = []
    frags = link_fragments(cands, settings, nominal_model.nominal)
    if frags.shape[1] < 3:
        return np.full((len(cands), frags.shape[1], 2), np.nan), warnings
    geo = ViewModel(nominal_model.nominal, "fixed")
    no_k = np.zeros((len(cands), 0))
    longest = np.argsort(-np.isfinite(frags[..., 0]).sum(0))[:max_rough_points]
    state, _, _ = rough_solve(nominal_model, frags[:, np.sort(longest)])
    rough = geo.geometry(ViewState(state.R, state.t, no_k))
    fxyz = triangulate_least_squares(*marker_rays(rough, frags))
    frags, rms = merge_fragments(frags, rough, fxyz, max(1.5, 0.35 * settings.diameter_px), 15.0)
    uv = frags[:, np.isfinite(rms) & (rms < max(2.0, 0.5 * settings.diameter_px))]
    det = nominal_model.nominal.detector
    margin = 0.5 * settings.diameter_px + 1.0
    for _ in range(4):
        if uv.shape[1] < 3:
            break
        k_before = uv.shape[1]
        state, xyz, _ = rough_solve(nominal_model, uv)
        err = np.linalg.norm(geo.project(ViewState(state.R, state.t, no_k), xyz) - uv, axis=-1)
        with np.errstate(invalid="ignore"):
            med = np.nanmedian(err, axis=0)
        consistent = med < max(1.0, 3.0 * float(np.nanmedian(med)))
        uv, xyz = uv[:, consistent], xyz[consistent]
        xyz = _merge_close(xyz, uv, diameter_mm)
        predicted = geo.project(ViewState(state.R, state.t, no_k), xyz)
        inside = (
            (predicted[..., 0] >= margin)
            & (predicted[..., 0] <= det.cols - 1 - margin)
            & (predicted[..., 1] >= margin)
            & (predicted[..., 1] <= det.rows - 1 - margin)
        )
        predicted[~inside] = np.nan
        uv = assign_to_predictions(cands, predicted, settings, gate_px=max(2.0, 0.5 * settings.diameter_px))
        # a real BB is found in a good share of the frames where it should be visible
        found = np.isfinite(uv).all(-1).sum(0)
        expected = np.isfinite(predicted).all(-1).sum(0)
        uv = uv[:, (found >= settings.min_fragment) & (found >= min_found_share * expected)]
        if uv.shape[1] == k_before:
            break
    count = np.isfinite(uv).all(-1).sum(0)
    keep = count >= min_observations
    if (~keep).any():
        warnings.append(f"dropped {int((~keep).sum())} BB candidate(s) seen in fewer than {min_observations} frames")
    uv = uv[:, keep]
    order = np.argsort(np.nanargmax(np.isfinite(uv).all(-1), axis=0) if uv.shape[1] else [])
    return uv[:, order], warnings
