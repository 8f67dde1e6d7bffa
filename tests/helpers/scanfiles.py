"""Small scan files written directly, for what acquisition should never write but a file may hold."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from orbitct.geometry import Panel, ViewGeometry
from orbitct.scanfile import ScanWriter

PANEL = Panel(8, 10, 1.5, 1.25)


def write_sweep_ahead_scan(path: Path) -> None:
    """Six projections 2 deg apart; two read back far from their command (5 and 9.5 deg behind), as a sweep that
    ran ahead of its exposures recorded them (a DCArc in continuous mode, before the fix)."""
    geom = ViewGeometry.from_carm(np.linspace(0, 1, 6), 0.1, 785.0, 1200.0, PANEL)
    w = ScanWriter(
        path,
        PANEL,
        axes={"stage.angle": "deg", "hexapod.U": "deg"},
        orbit_name="circular",
        orbit_params={"n_frames": 6},
        config={"sad_mm": 785.0},
    )
    behind = [0.0, 0.4, 0.9, 5.0, 9.5, 0.2]
    for i in range(6):
        w.append(
            np.full(PANEL.shape, 9000, np.uint16),
            "projection",
            float(i),
            nominal_vector=geom.vectors[i],
            encoders={"stage.angle": 2.0 * i + behind[i], "hexapod.U": 0.0},
            commanded={"stage.angle": 2.0 * i, "hexapod.U": 0.0},
        )
    w.finish()
