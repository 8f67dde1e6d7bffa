"""Grey windows and slice figures of a reconstruction: anatomy stays visible when metal is present."""

from __future__ import annotations

import numpy as np

from recon.export import display_window


def _phantom(with_metal: bool) -> np.ndarray:
    rng = np.random.default_rng(0)
    z, y, x = np.mgrid[:32, :64, :64]
    r = np.hypot(y - 32, x - 32)
    vol = np.where(r < 28, 0.02, 0.0) + np.where(r < 10, 0.005, 0.0)  # water with a slightly denser insert
    vol = vol + rng.normal(0, 5e-4, vol.shape)
    if with_metal:
        vol[:, 40:44, 40:44] = 0.8  # a steel screw, 40 times water
    return vol.astype(np.float32)


def test_metal_does_not_push_the_anatomy_into_black() -> None:
    lo0, hi0, note0 = display_window(_phantom(False))
    lo, hi, note = display_window(_phantom(True))
    assert note0 == "" and "metal" in note
    assert hi < 0.05  # the window stays on soft tissue: the insert (0.025) is inside it, not crushed to black
    assert abs(hi - hi0) < 0.2 * hi0 and abs(lo - lo0) < 0.005


def test_all_nan_or_constant_volume_gives_a_usable_window() -> None:
    assert display_window(np.full((4, 4, 4), np.nan, np.float32))[:2] == (0.0, 1.0)
    lo, hi, _ = display_window(np.zeros((4, 4, 4), np.float32))
    assert hi > lo
