"""Errors raised by reconstruction."""


class ReconError(ValueError):
    """Reconstruction input or setting that cannot be used; the message says what is allowed."""


class GeometryMissingError(ReconError):
    """The scan file lacks the requested geometry group."""


class FieldOfViewError(ReconError):
    """The volume grid does not overlap the field of view of the views."""


class MemoryBudgetError(ReconError):
    """The reconstruction would need more memory than the machine has available."""
