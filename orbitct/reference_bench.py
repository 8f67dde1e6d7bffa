"""The bench of the published study (Ma et al., SPIE 2022): the one home of its numbers.

Every default that describes that bench (source and detector distances, the
427 mm flat panel and its 768 px readout, the 3.17 mm steel BBs) comes from here:
the simulator, the twins, the bench configuration and the tests use the same values.
"""

from __future__ import annotations

from orbitct.geometry import Panel

SAD_MM = 785.0  # source to isocenter
SDD_MM = 1200.0  # source to detector
PANEL_MM = 427.0  # side of the square panel
PANEL_PX = 768  # pixels per side at full resolution
PITCH_MM = 0.556  # pixel pitch at full resolution
BB_DIAMETER_MM = 3.17  # the steel BBs of experiment A


def reference_panel(size_px: int = PANEL_PX, pitch_mm: float | None = None) -> Panel:
    """The square panel read out at ``size_px`` pixels: 0.556 mm at 768 px, else 427 mm / size."""
    if int(size_px) < 8:
        raise ValueError(f"panel size must be at least 8 px, got {size_px}")
    if pitch_mm is not None:
        p = float(pitch_mm)
    else:
        p = PITCH_MM if int(size_px) == PANEL_PX else PANEL_MM / int(size_px)
    return Panel(int(size_px), int(size_px), p, p)
