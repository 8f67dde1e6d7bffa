"""Shared pieces of the acquisition tests: a small simulated bench configuration and request."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from acquire.config import BenchConfig, parse_config
from acquire.runner import ScanRequest

# small errors that the hexapod twin's workspace can always realise
SMALL_ERRORS = {
    "angle_amplitude_deg": (0.4, 0.3, 0.5),
    "angle_noise_deg": (0.05, 0.05, 0.05),
    "shift_amplitude_mm": (2.0, 1.5, 1.0),
    "shift_noise_mm": (0.3, 0.3, 0.3),
}


def small_config(size: int = 64, time_scale: float = 25.0, **overrides: Any) -> BenchConfig:
    """The default bench with a small detector, fast twins and few darks/flats."""
    data: dict[str, Any] = {
        "geometry": {"detector": {"rows": size, "cols": size}},
        "calibration_frames": {"darks_before": 2, "flats_before": 2, "darks_after": 1, "flats_after": 1},
        "motion": {"settle_ms": 1.0},
        "exposure": {"exposure_ms": 2.0, "frame_rate_hz": 8.0},
        "sim": {"time_scale": time_scale},
    }
    data.update(overrides)
    cfg = parse_config(data)
    assert isinstance(cfg, BenchConfig)
    return cfg


def small_request(out: Path, frames: int = 16, **kw: Any) -> ScanRequest:
    """A short sawtooth on the in-process twins with small injected errors."""
    args: dict[str, Any] = dict(
        config=small_config(),
        out=out,
        orbit="sawtooth",
        frames=frames,
        orbit_params={"amplitude_deg": 6.0},
        errors="custom",
        error_params=SMALL_ERRORS,
        seed=1,
        sim=True,
        overwrite=True,
    )
    args.update(kw)
    return ScanRequest(**args)
