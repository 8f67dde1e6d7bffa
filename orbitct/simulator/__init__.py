"""Projection simulator: exact line integrals, detector noise model, simulated bench, whole scan files."""

from orbitct.simulator.bench import (
    DEFAULT_DETECTOR_PX,
    DEFAULT_PITCH_MM,
    DEFAULT_SAD_MM,
    DEFAULT_SDD_MM,
    PANEL_MM,
    SimulatedBench,
    bench_detector,
)
from orbitct.simulator.detector import DetectorModel, gaussian_blur
from orbitct.simulator.projector import line_integral_stack, line_integrals
from orbitct.simulator.scan import DEFAULT_ORBITS, SimulationResult, resolve_orbit, simulate_scan

__all__ = [
    "DEFAULT_DETECTOR_PX",
    "DEFAULT_ORBITS",
    "DEFAULT_PITCH_MM",
    "DEFAULT_SAD_MM",
    "DEFAULT_SDD_MM",
    "PANEL_MM",
    "DetectorModel",
    "SimulatedBench",
    "SimulationResult",
    "bench_detector",
    "gaussian_blur",
    "line_integral_stack",
    "line_integrals",
    "resolve_orbit",
    "simulate_scan",
]
