"""Errors raised by reconstruction."""

from orbitct.scanfile import describe_frame_problems


class ReconError(ValueError):
    """Reconstruction input or setting that cannot be used; the message says what is allowed."""


class GeometryMissingError(ReconError):
    """The scan file lacks the requested geometry group."""


class FailedGeometryError(ReconError):
    """The calibrated geometry failed its quality check and using it anyway was not asked for."""

    def __init__(self, name: str, reasons: list[str], how: str = "set accept_failed_geometry") -> None:
        self.name, self.reasons = name, reasons
        super().__init__(self.sentence(how))

    @property
    def what(self) -> str:
        """What happened: the geometry failed its check, with the check's reasons."""
        why = f" ({'; '.join(self.reasons)})" if self.reasons else ""
        return f"{self.name}: its calibrated geometry failed its quality check{why}"

    def advice(self, how: str) -> str:
        """What to do, ``how`` naming the override in the caller's terms."""
        return (
            "calibrate it again (see 'When a calibration fails its quality check' in the documentation), reconstruct "
            f"from the nominal geometry, or {how} to use it anyway (recorded with the volume)"
        )

    def sentence(self, how: str) -> str:
        """What happened and what to do, in one sentence."""
        return f"{self.what}; {self.advice(how)}"


class FieldOfViewError(ReconError):
    """The volume grid does not overlap the field of view of the views."""


class MemoryBudgetError(ReconError):
    """The reconstruction would need more memory than the machine has available."""


class TooLongError(ReconError):
    """The reconstruction is estimated to take longer than the caller's limit; ``estimated_s`` says how long."""

    def __init__(self, message: str, estimated_s: float) -> None:
        self.estimated_s = estimated_s
        super().__init__(message)


class ReconExistsError(ReconError):
    """The scan file already holds a reconstruction of that name (replacing it must be asked for)."""

    def __init__(self, path: object, name: str) -> None:
        self.path, self.name = path, name
        super().__init__(f"{path}: already has a reconstruction named {name!r}")


class BadFramesError(ReconError):
    """Frames the reconstruction would need hold NaN, infinite, all-zero or saturated data; names them."""

    def __init__(self, path: object, problems: dict[int, str], n_used: int) -> None:
        self.problems = dict(problems)
        super().__init__(
            f"{path}: {len(problems)} of the {n_used} frames needed are unusable: "
            f"{describe_frame_problems(problems)}; a volume made from them would be wrong, so none is stored"
        )
