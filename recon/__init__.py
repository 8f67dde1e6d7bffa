"""Reconstruction for arbitrary cone-beam orbits: projectors, FDK, PWLS/SPS, MAR, exports."""

from typing import TYPE_CHECKING

from orbitct.geometry import VolumeGrid
from orbitct.lazy import make_lazy
from recon.errors import (
    BadFramesError,
    FailedGeometryError,
    FieldOfViewError,
    GeometryMissingError,
    MemoryBudgetError,
    ReconError,
    ReconExistsError,
    TooLongError,
)
from recon.options import DEFAULT_BETA, ReconstructionOptions

if TYPE_CHECKING:
    from recon.estimate import reconstruction_seconds
    from recon.fdk import fdk
    from recon.grid import check_fov, grid_for_geometry
    from recon.operator import Projector, backproject_voxels, projector
    from recon.pipeline import ReconResult, compare_reconstructions, reconstruct_scan
    from recon.pwls import pwls_sps
    from recon.pwls_setup import PwlsResult
    from recon.quality import reference_volume, rmse, wire_fwhm

# imported on first use: `import recon.options` (the CLI's and the service's options) loads no numerical kernels
make_lazy(
    __name__,
    {
        "reconstruction_seconds": "recon.estimate",
        "fdk": "recon.fdk",
        "check_fov": "recon.grid",
        "grid_for_geometry": "recon.grid",
        "Projector": "recon.operator",
        "backproject_voxels": "recon.operator",
        "projector": "recon.operator",
        "ReconResult": "recon.pipeline",
        "compare_reconstructions": "recon.pipeline",
        "reconstruct_scan": "recon.pipeline",
        "PwlsResult": "recon.pwls_setup",
        "pwls_sps": "recon.pwls",
        "reference_volume": "recon.quality",
        "rmse": "recon.quality",
        "wire_fwhm": "recon.quality",
    },
)

__all__ = [
    "DEFAULT_BETA",
    "BadFramesError",
    "FailedGeometryError",
    "FieldOfViewError",
    "GeometryMissingError",
    "MemoryBudgetError",
    "Projector",
    "PwlsResult",
    "ReconError",
    "ReconExistsError",
    "ReconResult",
    "ReconstructionOptions",
    "TooLongError",
    "VolumeGrid",
    "backproject_voxels",
    "check_fov",
    "compare_reconstructions",
    "fdk",
    "grid_for_geometry",
    "projector",
    "pwls_sps",
    "reconstruct_scan",
    "reconstruction_seconds",
    "reference_volume",
    "rmse",
    "wire_fwhm",
]
