"""What the PWLS solvers on the CPU (:mod:`recon.pwls`) and on the GPU (:mod:`recon.cuda_pwls`) share: the result,
the penalty's neighbourhood, the checks of a start, the penalty's absolute strength, and how a data term cuts its
views into ordered subsets and reads them."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, TypeVar, cast

import numpy as np
from numpy.typing import NDArray

from recon.errors import ReconError
from recon.operator import Projector

P = TypeVar("P", bound=Projector)


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


def ordered_subsets(
    A: Projector, y: Any, weights: Any | None, subsets: int, subset_views: list[NDArray[np.intp]] | None
) -> list[NDArray[np.intp]]:
    """The views of each ordered subset of a data term of ``A`` (given, or every ``subsets``-th view starting at each
    offset), after refusing projections or weights not of ``A``'s projection shape."""
    A.check_stacks(projections=y, weights=weights)
    if subset_views is None:
        n_views = A.proj_shape[0]
        subset_views = [np.arange(m, n_views, subsets) for m in range(subsets)]
    return [np.asarray(v, np.intp) for v in subset_views]


def subset_operator(A: P, views: NDArray[np.intp]) -> P | None:
    """``A`` restricted to ``views`` (``A`` itself for all of them, None for none), of ``A``'s kind."""
    if views.size == A.proj_shape[0]:
        return A
    return cast(P, A.subset(views)) if views.size else None


def view_rows(stack: Any, views: NDArray[np.intp]) -> NDArray[np.float32]:
    """The rows of ``stack`` (an array or anything sliceable along views) for ``views`` as contiguous float32 (a view
    of an array when the views are in a row)."""
    index = slice(int(views[0]), int(views[-1]) + 1) if views[-1] - views[0] == views.size - 1 else views
    return np.ascontiguousarray(stack[index], dtype=np.float32)
