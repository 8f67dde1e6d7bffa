"""Named errors of the calibration package."""

from __future__ import annotations


class CalibrationError(ValueError):
    """A scan cannot be calibrated as asked."""


class NoProjectionsError(CalibrationError):
    """The scan holds no projection frames (image key 0)."""


class NoNominalGeometryError(CalibrationError):
    """The scan has no nominal geometry to start from."""


class NoMarkersError(CalibrationError):
    """No BBs (or too few to fix any geometry) were found in the projections."""


class OptionError(CalibrationError):
    """An unknown method or option value."""


class BadFramesError(CalibrationError):
    """Frames the calibration needs hold NaN, infinite, all-zero or saturated data; names them."""


class FrameTooLargeError(CalibrationError):
    """One frame would need more memory to process than the machine has available."""
