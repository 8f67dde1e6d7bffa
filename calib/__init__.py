"""Geometric calibration of arbitrary cone-beam orbits from BBs on the object (Ma et al., SPIE 2022, and beyond)."""

from typing import TYPE_CHECKING

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
from orbitct.lazy import make_lazy

if TYPE_CHECKING:
    from calib.pipeline import calibrate_scan
    from calib.result import CalibrationResult, IterationStats

# imported on first use: `import calib.options` (the CLI's and the service's options) loads no numerical kernels
make_lazy(
    __name__,
    {"calibrate_scan": "calib.pipeline", "CalibrationResult": "calib.result", "IterationStats": "calib.result"},
)

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
