"""Analytic phantoms: primitives with exact chord lengths, the paper's experiment phantoms, a voxelizer."""

from orbitct.phantoms.chords import chord_lengths
from orbitct.phantoms.experiments import EXPERIMENTS, experiment_phantom
from orbitct.phantoms.materials import METALS, MU_PER_MM, mu_of
from orbitct.phantoms.phantom import Phantom
from orbitct.phantoms.primitives import PhantomError, Primitive, cylinder, ellipsoid, frame_from_axis, sphere
from orbitct.phantoms.voxelize import voxelize

__all__ = [
    "EXPERIMENTS",
    "METALS",
    "MU_PER_MM",
    "Phantom",
    "PhantomError",
    "Primitive",
    "chord_lengths",
    "cylinder",
    "ellipsoid",
    "experiment_phantom",
    "frame_from_axis",
    "mu_of",
    "sphere",
    "voxelize",
]
