"""How long a reconstruction will take, estimated before anything large is allocated.

The projectors' cost grows with the number of ray steps (views x pixels x planes crossed) and FDK's with views x
voxels. The rates are measured once per process on a small problem on this machine, so the estimate follows the
machine and its load; it is an estimate (rays that miss the volume cost less, caches behave differently at size).
"""

from __future__ import annotations

import functools
import time

import numpy as np

from orbitct.geometry import ViewGeometry, VolumeGrid

_PROBE = 64  # voxels per side and pixels per side of the measuring problem
_PROBE_VIEWS = 8


@functools.cache
def rates() -> tuple[float, float, float]:
    """Seconds per ray step of the forward and of the matched back projector, and per voxel and view of FDK."""
    from orbitct.reference_bench import PANEL_MM, SAD_MM, SDD_MM, reference_panel
    from recon.fdk import fdk
    from recon.operator import projector

    panel = reference_panel(_PROBE, PANEL_MM / _PROBE)
    geometry = ViewGeometry.from_carm(
        np.linspace(0.0, 2 * np.pi, _PROBE_VIEWS, endpoint=False), 0.0, SAD_MM, SDD_MM, panel
    )
    grid = VolumeGrid.centered((_PROBE,) * 3, panel.pitch_col * SAD_MM / SDD_MM)
    A = projector(grid, geometry)
    x = np.ones(grid.shape, np.float32)
    y = A(x)
    A.T(y), fdk(y, grid, geometry)  # compiled before timing

    def best(call: object) -> float:
        times = []
        for _ in range(3):
            t = time.perf_counter()
            call()  # type: ignore[operator]
            times.append(time.perf_counter() - t)
        return min(times)

    steps = _PROBE_VIEWS * _PROBE * _PROBE * _PROBE
    return (
        best(lambda: A(x)) / steps,
        best(lambda: A.T(y)) / steps,
        best(lambda: fdk(y, grid, geometry)) / (_PROBE_VIEWS * _PROBE**3),
    )


def reconstruction_seconds(
    algorithm: str,
    grid: VolumeGrid,
    n_views: int,
    rows: int,
    cols: int,
    iterations: int = 0,
    final_cost: bool = False,
) -> float:
    """Estimated wall time of FDK, or of PWLS (its FDK start, the surrogate's set-up, ``iterations`` passes and, when
    asked for, the final cost) on this machine now."""
    forward, back, per_voxel_view = rates()
    nz, ny, nx = grid.shape
    fdk_s = per_voxel_view * n_views * nz * ny * nx
    if algorithm == "fdk":
        return fdk_s
    steps = n_views * rows * cols * 0.5 * (nx + ny)  # a ray steps along its main axis, mostly x or y on C-arm orbits
    return fdk_s + steps * ((forward + back) * (iterations + 1) + (forward if final_cost else 0.0))


def describe_seconds(seconds: float) -> str:
    """'40 s', '12 min', '3.5 h'."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


__all__ = ["describe_seconds", "rates", "reconstruction_seconds"]
