"""Projection simulator: exact line integrals, detector noise model, simulated bench, whole scan files."""

from orbitct.simulator.beam import Beam
from orbitct.simulator.bench import (
    SimulatedBench,
)
from orbitct.simulator.detector import DetectorModel, gaussian_blur
from orbitct.simulator.projector import line_integral_stack, line_integrals
from orbitct.simulator.scan import DEFAULT_ORBITS, SimulationResult, resolve_orbit, simulate_scan

__all__ = [
    "DEFAULT_ORBITS",
    "Beam",
    "DetectorModel",
    "SimulatedBench",
    "SimulationResult",
    "gaussian_blur",
    "line_integral_stack",
    "line_integrals",
    "resolve_orbit",
    "simulate_scan",
]
