"""Geometric calibration of arbitrary cone-beam orbits from BBs on the object (Ma et al., SPIE 2022, and beyond)."""

from calib.errors import (
    BadFramesError,
    CalibrationError,
    FrameTooLargeError,
    NoMarkersError,
    NoNominalGeometryError,
    NoProjectionsError,
    OptionError,
)
from calib.options import METHODS, CalibrationOptions
from calib.pipeline import calibrate_scan
from calib.result import CalibrationResult, IterationStats

__all__ = [
    "METHODS",
    "BadFramesError",
    "CalibrationError",
    "CalibrationOptions",
    "CalibrationResult",
    "FrameTooLargeError",
    "IterationStats",
    "NoMarkersError",
    "NoNominalGeometryError",
    "NoProjectionsError",
    "OptionError",
    "calibrate_scan",
]
