"""What the PWLS solvers on the CPU (:mod:`recon.pwls`) and on the GPU (:mod:`recon.cuda_pwls`) share: the result,
the penalty's neighbourhood, the checks of a start and the penalty's absolute strength."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from recon.errors import ReconError


@dataclass
class PwlsResult:
    """Volume, cost per iteration and timing of a PWLS run: ``cost[k]`` is the cost at iterate ``k`` (0 = the start),
    up to the result's when ``final_cost`` was asked for, else up to the last iterate before it."""

    volume: NDArray[np.float32]
    cost: list[float] = field(default_factory=list)
    final_cost: bool = False  # whether cost[-1] is the result's
    iterations: int = 0
    elapsed_s: float = 0.0
    beta_abs: float = 0.0
    restarts: int = 0  # momentum restarts (the safeguard acting)


def neighbour_offsets(order: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Offsets ``(K, 3)`` (dz, dy, dx) of all neighbours and their weights 1/distance."""
    if order not in (1, 2):
        raise ReconError(f"penalty neighbourhood must be 1 (6 neighbours) or 2 (26 neighbours), got {order}")
    offs = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]
    if order == 1:
        offs = [o for o in offs if sum(map(abs, o)) == 1]
    arr = np.array(offs, dtype=np.int64)
    return arr, 1.0 / np.sqrt((arr**2).sum(1))


def checked_start(
    padded: tuple[int, ...],
    x0: NDArray[np.float32] | None,
    iterations: int,
    beta: float,
    data_curvature: NDArray[np.float32] | None,
) -> NDArray[np.float32] | None:
    """Refuse bad solver arguments in one sentence; returns ``x0`` when it is a padded start to update in place."""
    if iterations < 0 or beta < 0:
        raise ReconError(f"need iterations >= 0 and beta >= 0; got {iterations}, {beta}")
    vol_shape = tuple(n - 2 for n in padded)
    given_padded = x0 if x0 is not None and np.shape(x0) == padded else None
    if given_padded is not None and not (
        given_padded.dtype == np.float32 and given_padded.flags.c_contiguous and given_padded.flags.writeable
    ):
        raise ReconError("a padded x0 is updated in place: it must be a writeable C-contiguous float32 array")
    if x0 is not None and given_padded is None and np.shape(x0) != vol_shape:
        raise ReconError(f"x0: expected shape {vol_shape} (or padded {padded}), got {np.shape(x0)}")
    if data_curvature is not None and (data_curvature.shape != vol_shape or data_curvature.dtype != np.float32):
        raise ReconError(f"data_curvature: expected float32 of shape {vol_shape}, got {data_curvature.shape}")
    return given_padded


def absolute_beta(data_curvature: NDArray[np.float32], beta: float, omega: NDArray[np.float64]) -> float:
    """The penalty strength that makes an interior voxel's penalty curvature ``beta`` times the median positive
    data curvature (the median of a sub-lattice: no volume-sized copy)."""
    sample = data_curvature[::2, ::2, ::2]
    pos = sample[sample > 0]
    return float(beta * (np.median(pos) if pos.size else 0.0) / (2 * omega.sum()))
