"""Where a reconstruction runs: the CPU (the reference, always there) or one CUDA GPU.

``auto`` takes the GPU when one is usable and the CPU otherwise. A GPU is usable when the ``gpu`` extra is installed
(``pip install 'orbitct[gpu]'``: numba-cuda and the CUDA runtime's wheels) and the driver finds a device. Without the
extra nothing here imports CUDA. numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``, what the tests use) runs the
GPU kernels on the CPU, far slower than the CPU kernels: only an explicit ``cuda`` takes it, never ``auto``.
"""

from __future__ import annotations

import importlib.util
from typing import get_args

from orbitct.geometry import ViewGeometry, VolumeGrid
from recon.errors import ReconError
from recon.operator import Projector
from recon.options import Device

DEVICES: tuple[str, ...] = get_args(Device)


def simulated() -> bool:
    """Whether numba's CUDA simulator stands in for a GPU in this process."""
    from numba.core import config

    return bool(getattr(config, "ENABLE_CUDASIM", False))


def gpu_problem() -> str | None:
    """Why no GPU can be used here, in a sentence; None when one can."""
    if simulated():
        return None
    if importlib.util.find_spec("numba_cuda") is None:
        return "the GPU backend is not installed (pip install 'orbitct[gpu]')"
    from numba import cuda

    try:
        if not cuda.is_available():
            return "no CUDA GPU or driver was found"
        name = cuda.get_current_device().name
    except Exception as exc:  # noqa: BLE001 - the driver's own words go into the sentence
        return f"the CUDA driver cannot use the GPU ({str(exc).strip().splitlines()[0]})"
    return None if name else "no CUDA GPU was found"


def resolve_device(requested: str) -> str:
    """``cpu`` or ``cuda`` for a requested ``auto``, ``cpu`` or ``cuda``; a :class:`ReconError` in one sentence when
    ``cuda`` is asked for and cannot be used."""
    if requested not in DEVICES:
        raise ReconError(f"device must be one of {', '.join(DEVICES)}, got {requested!r}")
    if requested == "cpu":
        return "cpu"
    if requested == "auto":
        return "cuda" if not simulated() and gpu_problem() is None else "cpu"
    problem = gpu_problem()
    if problem is not None:
        raise ReconError(f"cannot reconstruct on the GPU: {problem}; use --device cpu or auto")
    return "cuda"


def describe_device(device: str) -> str:
    """The device in words, for outputs and result files: the CPU's threads or the GPU's name."""
    if device == "cpu":
        import numba

        return f"CPU ({numba.get_num_threads()} threads)"
    if simulated():
        return "CUDA simulator (numba, on the CPU)"
    from numba import cuda

    name = cuda.get_current_device().name
    return f"GPU {name.decode() if isinstance(name, bytes) else name}"


def from_the_gpu(exc: BaseException) -> bool:
    """Whether ``exc`` came from the CUDA driver or compiler (numba-cuda, cuda-python), not from orbitct."""
    return type(exc).__module__.startswith(("numba.cuda", "numba_cuda", "cuda."))


def make_projector(grid: VolumeGrid, geometry: ViewGeometry, device: str = "cpu") -> Projector:
    """The projection operator of ``grid`` seen by ``geometry`` on ``device`` (``cpu`` or ``cuda``)."""
    if device == "cuda":
        from recon.cuda import CudaProjector

        return CudaProjector(grid, geometry)
    return Projector(grid, geometry)
