"""Reconstruction for arbitrary cone-beam orbits: projectors, FDK, PWLS/SPS, MAR, exports."""

from orbitct.geometry import VolumeGrid
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
from recon.estimate import reconstruction_seconds
from recon.fdk import fdk
from recon.grid import check_fov, grid_for_geometry
from recon.operator import Projector, backproject_voxels, projector
from recon.options import ReconstructionOptions
from recon.pipeline import ReconResult, compare_reconstructions, reconstruct_scan
from recon.pwls import DEFAULT_BETA, PwlsResult, pwls_sps
from recon.quality import reference_volume, rmse, wire_fwhm

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
