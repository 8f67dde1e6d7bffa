"""What the object puts behind a BB's detection, predicted from a model of the object (a phantom).

Two things make one detection worse than another (experiment C at 512 px, 8000 detections against the truth):
the photons left behind the object — the centroid scatter grows with the line integral ``L`` under the BB, about
as ``exp(L)`` in variance (0.043 px per axis where ``exp(L - reference)`` is 0.07, 0.23 px where it is 3.5) — and a
background that is no plane across the detection window (bone edges, clutter, the object's own outline): the plane
fitted round the BB leaves a residual inside its disc that shifts the centroid, by up to 1 px. Both are computed
here per view and BB from the object's line integrals along rays through the detection window, as the detector
(:mod:`calib.detect`) sees it: the plane fitted to the ring round the BB, then the weighted centroid (positive
weights only) of the BB plus the residual against the BB's alone. The shift enters the prediction as a known
offset of each detection, carried through the bundle's normal equations (part of it is a BB centre placed off),
with a scatter round it as a variance.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from calib.quality import centroid_noise_px
from calib.surfaces import TapeSurface
from orbitct.geometry import ViewGeometry
from orbitct.phantoms.materials import mu_of

#: line integrals (unitless) along rays: origins and unit directions ``(N, 3)`` -> ``(N,)``
LineIntegral = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]

#: the detections' scatter beyond the photons' share: ``noise**2 * (exp(L - reference) + PHOTON_FLOOR)`` fits
#: experiment C at 512 px (detections without a computed shift: 0.043 px per axis at a photon factor of 0.07, 0.106
#: at 0.85, 0.228 at 3.5)
PHOTON_FLOOR = 0.1
#: the shift computed here is the detector's on a sharp frame (within 0.01 px over a tissue edge, tested); the
#: simulated panel's blur, like a real panel's, widens the BB and the edge: the measured shifts are 1.55 (experiment
#: A, clutter and wall; correlation 0.96 with the computed) to 1.75 (C, bone and outline; 0.69) times the computed
#: ones at 512 px (least squares over 1900 and 8000 detections against the truth)
SHIFT_FACTOR = 1.65
#: what the measured shifts scatter round SHIFT_FACTOR times the computed one, as a share of the computed one:
#: 0.31 (A) to 0.86 (C), beyond the photons' share
SHIFT_SCATTER = 0.6
#: the pixel noise the detector measures round a BB over the one its centroid's scatter implies on a sharp panel: a
#: panel's blur makes neighbouring pixels' noise alike, which moves a centroid more than independent noise would
#: (spirals on experiments A, B and C at 512 px: the background RMS computed with it ranks the measured one with
#: Spearman 0.92-0.95, median ratio 0.96-1.13)
PIXEL_NOISE_FACTOR = 0.5
#: BBs (in views) whose background is kept for the next request, the oldest dropped first: a plan asks for a few
#: hundred; at 500 views one costs 12 kB
CACHED_BBS = 4096


@dataclass(frozen=True)
class ObjectBackground:
    """The object behind the BBs: its line integrals along rays (without the BBs), the line integral at which the
    photon factor is 1 (``reference``: where ``exp(L)`` has its mean over BBs spread on the object's surface) and
    what such BBs see (``typical``: a calibration's centroid noise is the RMS of all its residuals, shifts
    included, and :meth:`random_noise_px` takes the shifts out again)."""

    line_integral: LineIntegral
    reference: float
    typical: NDArray[np.float64] | None = None  # (M, 3): photon factor and computed shift of BBs spread on the surface
    bb_mu_per_mm: float = field(default_factory=lambda: mu_of("steel"))
    _cache: dict[tuple[bytes, bytes, float], NDArray[np.float64]] = field(
        default_factory=dict, compare=False, repr=False
    )
    _random: dict[float, float] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def of(
        cls,
        line_integral: LineIntegral,
        geometry: ViewGeometry,
        surface: TapeSurface,
        diameter_mm: float,
    ) -> ObjectBackground:
        """The background of an object seen by ``geometry``, its reference and typical shift taken over BBs of
        ``diameter_mm`` spread over the tape ``surface`` (where BBs go), in about 60 of the views."""
        angle, z = np.meshgrid(
            np.linspace(0, 2 * np.pi, 16, endpoint=False), np.linspace(surface.z_min_mm, surface.z_max_mm, 7)
        )
        keep = surface.covers(angle.ravel(), z.ravel())
        if not keep.any():  # a surface with holes at every sample: no typical BB to refer to
            return cls(line_integral, 0.0, None)
        pts = surface.points(angle.ravel()[keep], z.ravel()[keep], diameter_mm)
        sub = geometry[:: max(1, geometry.n_views // 60)]
        direction = pts[None] - sub.S[:, None]
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        origin = np.broadcast_to(sub.S[:, None], direction.shape)
        values = line_integral(origin.reshape(-1, 3), direction.reshape(-1, 3))
        # the centroid noise a calibration reports is the RMS over its detections: the photon factor's mean there is 1
        reference = float(np.log(np.mean(np.exp(values - values.max())))) + float(values.max())
        probe = cls(line_integral, reference)
        photons, shift = probe._computed(sub, pts, diameter_mm)
        return cls(line_integral, reference, np.concatenate([photons[..., None], shift], -1).reshape(-1, 3))

    def random_noise_px(self, noise_px: float) -> float:
        """The centroid noise of the photons alone (at the reference) for a reported one: what makes residuals of
        BBs spread on the surface — photons, shifts and their scatter — have ``noise_px`` as the robust RMS a
        calibration reports (:func:`calib.quality.centroid_noise_px`); at least a quarter of it."""
        if self.typical is None or not len(self.typical):
            return float(noise_px)
        if noise_px not in self._random:
            self._random[noise_px] = self._random_noise_px(noise_px)
        return self._random[noise_px]

    def _random_noise_px(self, noise_px: float) -> float:
        assert self.typical is not None
        rng = np.random.default_rng(0)
        f = (self.typical[:, 0] + PHOTON_FLOOR) / (1.0 + PHOTON_FLOOR)
        shift = self.typical[:, 1:]
        z1, z2 = rng.normal(size=shift.shape), rng.normal(size=(len(shift), 1))
        fixed = SHIFT_FACTOR * shift + SHIFT_SCATTER * shift * z2

        def reported(sigma: float) -> float:
            return centroid_noise_px(sigma * np.sqrt(f)[:, None] * z1 + fixed)

        lo, hi = 0.25 * noise_px, noise_px
        if reported(lo) >= noise_px:
            return float(lo)
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if reported(mid) < noise_px else (lo, mid)
        return float(0.5 * (lo + hi))

    def variance(
        self, geometry: ViewGeometry, xyz: NDArray[np.float64], diameter_mm: float, noise_px: float
    ) -> NDArray[np.float64]:
        """Per view of ``geometry`` and BB ``xyz`` (K, 3), the detection's random covariance relative to
        ``noise_px**2`` ``(P, K, 2, 2)``: ``exp(L - reference)`` for the photons, plus :data:`SHIFT_SCATTER` times
        the computed centroid shift, squared."""
        photons, shift = self._computed(geometry, xyz, diameter_mm)
        return (photons + PHOTON_FLOOR)[..., None, None] / (1.0 + PHOTON_FLOOR) * np.eye(2) + (
            SHIFT_SCATTER / noise_px
        ) ** 2 * np.einsum("pka,pkb->pkab", shift, shift)

    def background_rms(
        self, geometry: ViewGeometry, xyz: NDArray[np.float64], diameter_mm: float, noise_px: float
    ) -> NDArray[np.float64]:
        """Per view and BB, the RMS of the background plane's residual round the detection ``(P, K)`` (line
        integral), as the detector measures it (``background_rms``, which weights the detection in the bundle): the
        structure the plane leaves, and the pixel noise that makes a centroid scatter by ``noise_px`` (the
        photons' share, at the reference) times :data:`PIXEL_NOISE_FACTOR`."""
        cols = self._columns(geometry, xyz, diameter_mm)
        f = (cols[..., 0] + PHOTON_FLOOR) / (1.0 + PHOTON_FLOOR)
        pixel = PIXEL_NOISE_FACTOR * noise_px * np.sqrt(f) / np.maximum(cols[..., 4], 1e-12)
        return np.sqrt(pixel**2 + cols[..., 3] ** 2)

    def bias(self, geometry: ViewGeometry, xyz: NDArray[np.float64], diameter_mm: float) -> NDArray[np.float64]:
        """Per view and BB, the centroid's offset the background causes ``(P, K, 2)`` (px): :data:`SHIFT_FACTOR`
        times the computed shift."""
        return SHIFT_FACTOR * self._computed(geometry, xyz, diameter_mm)[1]

    def _computed(
        self, geometry: ViewGeometry, xyz: NDArray[np.float64], diameter_mm: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Photon factors ``(P, K)`` and computed shifts ``(P, K, 2)``."""
        out = self._columns(geometry, xyz, diameter_mm)
        return out[..., 0], out[..., 1:3]

    def _columns(self, geometry: ViewGeometry, xyz: NDArray[np.float64], diameter_mm: float) -> NDArray[np.float64]:
        """:meth:`_one` for every BB ``(P, K, 5)``, cached per BB and views (by their content: a planner asks again
        for the BBs it keeps; at most :data:`CACHED_BBS`)."""
        out = np.empty((geometry.n_views, len(xyz), 5))
        panel = geometry.panel
        views = hashlib.blake2b(geometry.vectors.tobytes() + repr(panel).encode(), digest_size=16).digest()
        for k, point in enumerate(np.asarray(xyz, float)):
            key = (views, point.tobytes(), float(diameter_mm))
            if key not in self._cache:
                while len(self._cache) >= CACHED_BBS:
                    del self._cache[next(iter(self._cache))]  # the oldest
                self._cache[key] = self._one(geometry, point, diameter_mm)
            out[:, k] = self._cache[key]
        return out

    def _one(self, geometry: ViewGeometry, point: NDArray[np.float64], diameter_mm: float) -> NDArray[np.float64]:
        """``(P, 5)``: of one BB in every view, the photon factor, the centroid shift (px), the RMS of the structure
        the background plane leaves in the ring round the BB (line integral) and the centroid's move per unit of
        pixel noise (px per line integral)."""
        uv = geometry.project(point[None])[:, 0]  # (P, 2)
        det = geometry.panel
        pitch = float(np.sqrt(det.pitch_col * det.pitch_row))
        to_panel = np.linalg.norm(geometry.pixel_to_point(uv[:, None])[:, 0] - geometry.S, axis=1)
        d_px = diameter_mm * to_panel / np.linalg.norm(point - geometry.S, axis=1) / pitch  # at the BB's depth
        r = 0.5 * d_px
        half = np.ceil(d_px) + 2.0  # the detector's window, centred on the BB's nearest pixel
        reach = int(half.max())
        o = np.arange(-reach, reach + 1, dtype=float)
        ox, oy = (a.ravel() for a in np.meshgrid(o, o))
        # every pixel of the disc's box, every other one (a checkerboard) of the rest of the window
        box = np.maximum(np.abs(ox), np.abs(oy)) <= np.ceil(r.max() + 1.0)
        take = box | ((ox + oy) % 2 == 0)
        ox, oy = ox[take], oy[take]
        pixels = np.floor(uv + 0.5)[:, None] + np.stack([ox, oy], -1)[None]  # (P, M, 2)
        rel = pixels - uv[:, None]
        dist2 = (rel**2).sum(-1)
        in_window = np.maximum(np.abs(ox), np.abs(oy))[None] <= half[:, None]
        in_disc = dist2 <= ((r + 0.75) ** 2)[:, None]
        ring = in_window & (dist2 >= ((r + 1.0) ** 2)[:, None]) & ((ox + oy) % 2 == 0)[None]
        origin, direction = geometry.backproject(pixels)
        values = self.line_integral(
            np.broadcast_to(origin, direction.shape).reshape(-1, 3), direction.reshape(-1, 3)
        ).reshape(pixels.shape[:2])
        design = np.concatenate([np.ones(rel.shape[:2] + (1,)), rel], -1) * ring[..., None]  # plane about the centre
        coef = np.linalg.solve(
            np.einsum("pma,pmb->pab", design, design), np.einsum("pma,pm->pa", design, values)[..., None]
        )[..., 0]
        residual = np.where(in_disc, values - (coef[:, None, 0] + np.einsum("pma,pa->pm", rel, coef[:, 1:])), 0.0)
        # the BB's own line integrals (its chords, averaged over 3 x 3 points of each pixel), then the detector's
        # weighted centroid over the disc of BB plus residual (only positive weights count) against the BB's alone
        sub = np.array([-1.0, 0.0, 1.0]) / 3.0
        ss = np.stack(np.meshgrid(sub, sub), -1).reshape(-1, 2)
        rho2 = ((rel[:, :, None] + ss[None, None]) ** 2).sum(-1) / (0.5 * d_px[:, None, None]) ** 2
        ball = (self.bb_mu_per_mm * diameter_mm * np.sqrt(np.maximum(1.0 - rho2, 0.0))).mean(-1) * in_disc
        weight = np.where(in_disc, np.maximum(ball + residual, 0.0), 0.0)
        total = weight.sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            shift = (
                np.einsum("pm,pma->pa", weight, rel) / total[:, None]
                - np.einsum("pm,pma->pa", ball, rel) / ball.sum(1)[:, None]
            )
        # a background falling away faster than the BB rises leaves it nothing to weigh: half a diameter off
        shift = np.where((total > 0)[:, None], shift, 0.5 * d_px[:, None])
        photons = np.exp(np.clip(coef[:, 0] - self.reference, -20.0, 20.0))
        # what the detector's background RMS sees of the structure: the plane's residual over the ring
        plane = coef[:, None, 0] + np.einsum("pma,pa->pm", rel, coef[:, 1:])
        structure = np.sqrt((np.where(ring, values - plane, 0.0) ** 2).sum(1) / np.maximum(ring.sum(1), 1))
        # a pixel's noise moves the weighted centroid by its offset over the BB's summed weight
        leverage = np.sqrt((np.where(in_disc, rel[..., 0] ** 2, 0.0)).sum(1)) / np.maximum(ball.sum(1), 1e-12)
        return np.concatenate([photons[:, None], shift, structure[:, None], leverage[:, None]], 1)


def phantom_background(
    phantom: object, geometry: ViewGeometry, surface: TapeSurface, diameter_mm: float | None = None
) -> ObjectBackground:
    """The background of a phantom (:class:`orbitct.phantoms.phantom.Phantom`) without its BBs, for BBs of
    ``diameter_mm`` (default: the phantom's)."""
    d = float(diameter_mm if diameter_mm is not None else phantom.marker_diameter_mm)  # type: ignore[attr-defined]
    bare = phantom.with_markers(np.zeros((0, 3)), d)  # type: ignore[attr-defined]
    return ObjectBackground.of(bare.line_integral, geometry, surface, d)


__all__ = [
    "PHOTON_FLOOR",
    "PIXEL_NOISE_FACTOR",
    "SHIFT_FACTOR",
    "SHIFT_SCATTER",
    "LineIntegral",
    "ObjectBackground",
    "phantom_background",
]
