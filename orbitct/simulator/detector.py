"""Flat-panel detector model: gain pattern, blur, quantum (Poisson) noise, dark offset, read noise, saturation; and,
each off unless asked for, what makes a real panel's images less clean: scatter, lag and dead pixels."""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, model_validator

from orbitct.reference_bench import PITCH_MM
from orbitct.simulator.noise import normal_fast, poisson, seed_from, stream


@nb.njit(parallel=True, cache=True, nogil=True)
def _signal_rows(li: NDArray[np.float32], flat: NDArray[np.float32], k: NDArray[np.float32]) -> NDArray[np.float32]:
    """``flat * exp(-li)`` blurred along rows with kernel ``k`` (edges clamped)."""
    rows, cols = li.shape
    r = (k.shape[0] - 1) // 2
    out = np.empty((rows, cols), dtype=np.float32)
    for i in nb.prange(rows):
        buf = np.empty(cols, dtype=np.float32)
        for j in range(cols):
            buf[j] = flat[i, j] * math.exp(-float(li[i, j]))
        for j in range(cols):
            acc = 0.0
            if r <= j < cols - r:
                for q in range(-r, r + 1):
                    acc += k[q + r] * buf[j + q]
            else:
                for q in range(-r, r + 1):
                    acc += k[q + r] * buf[min(max(j + q, 0), cols - 1)]
            out[i, j] = acc
    return out


@nb.njit(parallel=True, cache=True, nogil=True)
def _blur_cols(img: NDArray[np.float32], k: NDArray[np.float32]) -> NDArray[np.float32]:
    rows, cols = img.shape
    r = (k.shape[0] - 1) // 2
    out = np.empty_like(img)
    for i in nb.prange(rows):
        for j in range(cols):
            acc = 0.0
            for q in range(-r, r + 1):
                acc += k[q + r] * img[min(max(i + q, 0), rows - 1), j]
            out[i, j] = acc
    return out


@nb.njit(parallel=True, cache=True, nogil=True)
def _readout(
    rows_blurred: NDArray[np.float32],
    k: NDArray[np.float32],
    gain: float,
    dark: NDArray[np.float32],
    read_noise: float,
    sat: float,
    seed: np.uint64,
) -> NDArray[np.uint16]:
    """Column blur, then Poisson quanta (mean signal / gain) times gain, plus dark and read noise, clipped."""
    rows, cols = rows_blurred.shape
    r = (k.shape[0] - 1) // 2
    out = np.empty((rows, cols), dtype=np.uint16)
    for i in nb.prange(rows):
        for j in range(cols):
            mean = 0.0
            for q in range(-r, r + 1):
                mean += k[q + r] * rows_blurred[min(max(i + q, 0), rows - 1), j]
            st = stream(seed, i * cols + j)
            st, n = poisson(st, mean / gain)
            st, z = normal_fast(st)
            x = n * gain + dark[i, j] + read_noise * z
            x = min(max(x, 0.0), sat)
            out[i, j] = np.uint16(math.floor(x + 0.5))
    return out


@nb.njit(parallel=True, cache=True, nogil=True)
def _quanta(
    rows_blurred: NDArray[np.float32], k: NDArray[np.float32], gain: float, seed: np.uint64
) -> NDArray[np.float32]:
    """Column blur, then the detected quanta (Poisson, mean signal / gain) times gain: ADU above dark, no read-out."""
    rows, cols = rows_blurred.shape
    r = (k.shape[0] - 1) // 2
    out = np.empty((rows, cols), dtype=np.float32)
    for i in nb.prange(rows):
        for j in range(cols):
            mean = 0.0
            for q in range(-r, r + 1):
                mean += k[q + r] * rows_blurred[min(max(i + q, 0), rows - 1), j]
            _, n = poisson(stream(seed, i * cols + j), mean / gain)
            out[i, j] = n * gain
    return out


@nb.njit(parallel=True, cache=True, nogil=True)
def _read_out(
    signal: NDArray[np.float32], dark: NDArray[np.float32], read_noise: float, sat: float, seed: np.uint64
) -> NDArray[np.uint16]:
    """Signal (ADU above dark) plus dark and read noise, clipped and rounded to the panel's integers."""
    rows, cols = signal.shape
    out = np.empty((rows, cols), dtype=np.uint16)
    for i in nb.prange(rows):
        for j in range(cols):
            _, z = normal_fast(stream(seed, i * cols + j))
            x = min(max(signal[i, j] + dark[i, j] + read_noise * z, 0.0), sat)
            out[i, j] = np.uint16(math.floor(x + 0.5))
    return out


def blur_kernel(sigma_px: float) -> NDArray[np.float32]:
    """Normalised 1-D Gaussian taps (radius 3 sigma); ``[1]`` for no blur."""
    if sigma_px <= 0:
        return np.ones(1, np.float32)
    r = max(1, int(math.ceil(3.0 * sigma_px)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma_px) ** 2)
    return (k / k.sum()).astype(np.float32)


def gaussian_blur(img: NDArray[np.float32], sigma_px: float) -> NDArray[np.float32]:
    """Separable Gaussian blur (edges clamped) of a float32 image."""
    k = blur_kernel(sigma_px)
    return _blur_cols(_signal_rows(np.zeros(img.shape, np.float32), np.ascontiguousarray(img, np.float32), k), k)


class DetectorModel(BaseModel):
    """Raw-count model of an indirect flat panel (defaults: a 16-bit panel at a moderate dose)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    flat_counts: float = Field(16000.0, gt=0, le=65535, description="mean open-field signal above dark, ADU")
    gain_adu: float = Field(4.0, gt=0, description="ADU per detected X-ray quantum (sets the Poisson noise)")
    dark_offset_adu: float = Field(300.0, ge=0, description="mean dark offset, ADU")
    dark_pattern_adu: float = Field(4.0, ge=0, description="fixed-pattern spread of the dark offset, ADU")
    read_noise_adu: float = Field(3.0, ge=0, description="electronic read noise (std), ADU")
    blur_sigma_px: float = Field(
        0.6, ge=0, le=10, description="the panel's own blur: scintillator and pixel (Gaussian std), pixels"
    )
    focal_blur_mm: float = Field(
        0.0,
        ge=0,
        le=5,
        description="the focal spot's blur at the detector (Gaussian std, mm): geometric, so the same in millimetres "
        "whatever the pixel pitch; it adds to blur_sigma_px in quadrature and acts before the quanta are counted",
    )
    gain_variation: float = Field(0.02, ge=0, le=0.5, description="pixel-to-pixel gain spread (fraction)")
    falloff: float = Field(0.10, ge=0, le=0.9, description="flat-field drop from centre to corner (heel/distance)")
    pattern_seed: int = Field(7, description="seed of the fixed gain and dark patterns")
    saturation_adu: float = Field(65535.0, gt=0, le=65535, description="largest raw value (uint16)")
    scatter_fraction: float = Field(
        0.0,
        ge=0,
        le=2,
        description="scattered radiation: the scatter-to-primary ratio behind one attenuation length of the object "
        "(scatter grows with the object's line integral l as l * exp(-l) and spreads widely over the panel)",
    )
    scatter_width: float = Field(
        0.08, gt=0, le=1, description="how widely scatter spreads: its Gaussian std as a fraction of the panel width"
    )
    lag_fraction: float = Field(
        0.0, ge=0, le=0.3, description="image lag: the share of each frame's signal read out with the next frame"
    )
    dead_pixel_fraction: float = Field(
        0.0, ge=0, le=0.05, description="pixels that read their dark offset whatever the exposure (fixed, seeded)"
    )
    dead_columns: int = Field(0, ge=0, le=64, description="whole columns that read their dark offset (fixed, seeded)")
    noise_blur_px: float = Field(
        0.0,
        ge=0,
        le=10,
        description="the share of blur_sigma_px that spreads each detected quantum's light in the scintillator "
        "(Gaussian std, pixels): it blurs the noise too, so neighbouring pixels' noise is correlated as on every "
        "indirect panel; the rest of the blur (focal spot) acts on the image before the quanta are counted",
    )

    @model_validator(mode="after")
    def _noise_blur_within_blur(self) -> DetectorModel:
        if self.noise_blur_px > self.blur_sigma_px:
            raise ValueError(
                f"noise_blur_px ({self.noise_blur_px:g}) is part of blur_sigma_px ({self.blur_sigma_px:g}) "
                "and cannot exceed it"
            )
        return self

    _maps: dict[tuple[int, int], tuple[NDArray[np.float32], NDArray[np.float32]]] = PrivateAttr(default_factory=dict)
    _dead: dict[tuple[int, int], NDArray[np.bool_]] = PrivateAttr(default_factory=dict)
    _last_signal: dict[tuple[int, int], NDArray[np.float32]] = PrivateAttr(default_factory=dict)

    @classmethod
    def preset(cls, name: str) -> DetectorModel:
        """A named model: ``clean`` (the defaults) or ``realistic`` (a C-arm's flat panel as labs meet it: wider
        blur from scintillator and focal spot, scatter, lag, dead pixels and two dead columns)."""
        if name not in PRESETS:
            raise ValueError(f"unknown detector preset {name!r}; choose from {sorted(PRESETS)}")
        return cls(**PRESETS[name])

    def maps(self, shape: tuple[int, int]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Fixed mean open-field signal (ADU above dark) and dark maps for a frame shape."""
        if shape not in self._maps:
            rows, cols = shape
            rng = np.random.default_rng([self.pattern_seed, rows, cols])
            y, x = np.meshgrid(np.linspace(-1, 1, rows), np.linspace(-1, 1, cols), indexing="ij")
            smooth = 1.0 - self.falloff * (0.5 * (x**2 + y**2) + 0.15 * y) / 1.15
            pixel = 1.0 + self.gain_variation * rng.standard_normal(shape)
            flat = (self.flat_counts * smooth * pixel).astype(np.float32)
            dark = (self.dark_offset_adu + self.dark_pattern_adu * rng.standard_normal(shape)).astype(np.float32)
            self._maps[shape] = (flat, dark)
        return self._maps[shape]

    def dead(self, shape: tuple[int, int]) -> NDArray[np.bool_]:
        """The fixed map of dead pixels (and dead columns) for a frame shape."""
        if shape not in self._dead:
            rng = np.random.default_rng([self.pattern_seed, shape[0], shape[1], 1])
            dead = rng.random(shape) < self.dead_pixel_fraction
            dead[:, rng.choice(shape[1], size=min(self.dead_columns, shape[1]), replace=False)] = True
            self._dead[shape] = dead
        return self._dead[shape]

    def scatter(self, li: NDArray[np.float32]) -> NDArray[np.float32]:
        """Mean scattered signal (ADU) for line integrals ``li``: ``scatter_fraction * l * exp(-l)`` of the open
        field, spread by a wide Gaussian (computed on a coarse grid: scatter is smooth)."""
        flat, _ = self.maps(li.shape)
        if self.scatter_fraction <= 0:
            return np.zeros(li.shape, np.float32)
        li64 = np.maximum(np.asarray(li, dtype=np.float64), 0.0)
        source = self.scatter_fraction * flat * li64 * np.exp(-li64)
        step = max(1, li.shape[1] // 64)
        rows, cols = li.shape
        coarse = source[: rows - rows % step, : cols - cols % step]
        coarse = coarse.reshape(rows // step, step, cols // step, step).mean((1, 3)).astype(np.float32)
        spread = gaussian_blur(coarse, self.scatter_width * cols / step)
        r = np.minimum((np.arange(rows) + 0.5) / step - 0.5, spread.shape[0] - 1).clip(0)
        c = np.minimum((np.arange(cols) + 0.5) / step - 0.5, spread.shape[1] - 1).clip(0)
        r0, c0 = r.astype(int), c.astype(int)
        r1, c1 = np.minimum(r0 + 1, spread.shape[0] - 1), np.minimum(c0 + 1, spread.shape[1] - 1)
        wr, wc = (r - r0)[:, None], (c - c0)[None, :]
        top = spread[r0][:, c0] * (1 - wc) + spread[r0][:, c1] * wc
        bottom = spread[r1][:, c0] * (1 - wc) + spread[r1][:, c1] * wc
        return (top * (1 - wr) + bottom * wr).astype(np.float32)

    def blur_px(self, pitch_mm: float = PITCH_MM) -> float:
        """The whole blur (Gaussian std, pixels) on a panel of ``pitch_mm`` pixels: the panel's own and the focal
        spot's."""
        return math.hypot(self.blur_sigma_px, self.focal_blur_mm / pitch_mm)

    def mean_signal(self, li: NDArray[np.float32], pitch_mm: float = PITCH_MM) -> NDArray[np.float32]:
        """Noise-free mean signal above dark (ADU) for line integrals ``li`` on pixels of ``pitch_mm``, blurred,
        scatter included (lag, which depends on the frame before, is not)."""
        flat, _ = self.maps(li.shape)
        k = blur_kernel(self.blur_px(pitch_mm))
        rows = _signal_rows(np.ascontiguousarray(li, dtype=np.float32), flat, k)
        return _blur_cols(rows + self.scatter(li), k)

    def expected(self, li: NDArray[np.float32], pitch_mm: float = PITCH_MM) -> NDArray[np.float32]:
        """Noise-free mean raw value for line integrals ``li`` on pixels of ``pitch_mm`` (before saturation)."""
        return self.mean_signal(li, pitch_mm) + self.maps(li.shape)[1]

    def expose(
        self, li: NDArray[np.float32], rng: np.random.Generator, pitch_mm: float = PITCH_MM
    ) -> NDArray[np.uint16]:
        """One raw frame (uint16) for line integrals ``li`` (rows, cols) on pixels of ``pitch_mm``: blur, scatter,
        lag of the frame before, quantum noise, dark, read noise, dead pixels."""
        flat, dark = self.maps(li.shape)
        blur = self.blur_px(pitch_mm)
        mean_blur = blur if self.noise_blur_px == 0 else math.sqrt(blur**2 - self.noise_blur_px**2)
        k = blur_kernel(mean_blur)  # the blur before the quanta are counted (the rest spreads them)
        rows = _signal_rows(np.ascontiguousarray(li, dtype=np.float32), flat, k)
        if self.scatter_fraction > 0:
            rows += self.scatter(li)
        return self._read(rows, k, dark, rng)

    def _read(
        self, rows: NDArray[np.float32], k: NDArray[np.float32], dark: NDArray[np.float32], rng: np.random.Generator
    ) -> NDArray[np.uint16]:
        """Lag, read-out with noise, dead pixels: the steps every frame goes through."""
        shape = (int(rows.shape[0]), int(rows.shape[1]))
        if self.lag_fraction > 0:  # this frame keeps back a share of its signal; the one before gives its share
            before = self._last_signal.get(shape)
            self._last_signal[shape] = rows.copy()
            rows = (1.0 - self.lag_fraction) * rows + (self.lag_fraction * before if before is not None else 0.0)
            rows = np.ascontiguousarray(rows, dtype=np.float32)
        if self.noise_blur_px > 0:  # quanta counted, then each spread by the scintillator, then read out
            quanta = gaussian_blur(_quanta(rows, k, float(self.gain_adu), seed_from(rng)), self.noise_blur_px)
            out = _read_out(quanta, dark, float(self.read_noise_adu), float(self.saturation_adu), seed_from(rng))
        else:
            out = _readout(
                rows,
                k,
                float(self.gain_adu),
                dark,
                float(self.read_noise_adu),
                float(self.saturation_adu),
                seed_from(rng),
            )
        if self.dead_pixel_fraction > 0 or self.dead_columns > 0:
            dead = self.dead(shape)
            out[dead] = np.clip(np.rint(dark[dead]), 0, self.saturation_adu).astype(np.uint16)
        return out

    def flat(self, rng: np.random.Generator, shape: tuple[int, int], pitch_mm: float = PITCH_MM) -> NDArray[np.uint16]:
        """One open-field (flat) frame on pixels of ``pitch_mm`` (blurred as a projection is)."""
        return self.expose(np.zeros(shape, dtype=np.float32), rng, pitch_mm)

    def dark(self, rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.uint16]:
        """One dark frame (X-rays off; with lag, the frame before still shows faintly)."""
        _, dark = self.maps(tuple(shape))  # type: ignore[arg-type]
        return self._read(np.zeros(shape, np.float32), np.ones(1, np.float32), dark, rng)


#: named detector models (:meth:`DetectorModel.preset`)
PRESETS: dict[str, dict[str, float]] = {
    "clean": {},
    "realistic": {
        # a 0.6 mm focal spot seen at the isocentre's magnification, on top of the panel's own 0.6 px: 1.0 px in
        # all on the reference panel's 0.556 mm pixels, 0.72 px on 1.11 mm pixels (384 px)
        "focal_blur_mm": 0.8 * PITCH_MM,
        "scatter_fraction": 0.3,  # no anti-scatter grid behind a torso's worth of tissue
        "lag_fraction": 0.03,  # first-frame lag of an a-Si panel
        "dead_pixel_fraction": 0.001,
        "dead_columns": 2,
        "gain_variation": 0.03,
    },
}
