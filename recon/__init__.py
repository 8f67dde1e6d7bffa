"""Reconstruction for arbitrary cone-beam orbits: projectors, FDK, PWLS/SPS, MAR, exports."""

from recon.errors import FieldOfViewError, GeometryMissingError, MemoryBudgetError, ReconError
from recon.grid import VolumeGrid, check_fov, grid_for_geometry
from recon.operator import Projector, backproject_voxels, projector

__all__ = [
    "FieldOfViewError", "GeometryMissingError", "MemoryBudgetError", "Projector", "ReconError", "VolumeGrid",
    "backproject_voxels", "check_fov", "grid_for_geometry", "projector",
]
