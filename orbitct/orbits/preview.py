"""Picture of an orbit: source positions as dots on a unit sphere around the isocenter (like the paper's Fig. 1)."""

from __future__ import annotations

import os

import numpy as np

from orbitct.orbits.orbit import Orbit


def source_directions(orbit: Orbit) -> np.ndarray:
    """Unit vectors isocenter -> source ``(N, 3)`` in the object frame (``geometry.md``)."""
    th, ph = orbit.theta, orbit.phi
    return np.stack([np.sin(th) * np.cos(ph), -np.cos(th) * np.cos(ph), np.sin(ph)], axis=-1)


def draw_orbit(orbit: Orbit, out: str | os.PathLike[str], *, dpi: int = 120) -> None:
    """Write a PNG of ``orbit``: sphere wireframe, red isocenter, source dots coloured by frame order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = source_directions(orbit)
    fig = plt.figure(figsize=(6.4, 5.6))
    ax = fig.add_subplot(projection="3d")
    u, v = np.mgrid[0 : 2 * np.pi : 37j, -np.pi / 2 : np.pi / 2 : 19j]
    ax.plot_wireframe(np.cos(u) * np.cos(v), np.sin(u) * np.cos(v), np.sin(v), color="0.85", linewidth=0.4)
    sc = ax.scatter(d[:, 0], d[:, 1], d[:, 2], c=np.arange(orbit.n_frames), cmap="viridis", s=6, depthshade=False)
    ax.scatter([0], [0], [0], color="red", s=40)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z (rotation axis)")
    ax.view_init(elev=18, azim=-60)
    tdeg, pdeg = orbit.theta_deg, orbit.phi_deg
    ax.set_title(
        f"{orbit.name}: {orbit.n_frames} frames, {orbit.n_segments} part(s)\n"
        f"rotation {tdeg.min():.0f}..{tdeg.max():.0f} deg, tilt {pdeg.min():+.0f}..{pdeg.max():+.0f} deg",
        fontsize=10,
    )
    fig.colorbar(sc, ax=ax, shrink=0.6, label="frame")
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
