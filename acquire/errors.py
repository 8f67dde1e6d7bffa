"""Named errors of the acquisition package."""

from __future__ import annotations


class AcquireError(Exception):
    """Base of all acquisition errors."""


class ConfigError(AcquireError, ValueError):
    """A bench or C-arm configuration that cannot be used; the message names the field and the reason."""


class RefusedError(AcquireError):
    """Pre-flight refused the scan before anything moved; the message says why."""


class NotReadyError(RefusedError):
    """The bench cannot start a scan yet (axes not referenced): an operator's step comes first; the message names it."""


class PreflightError(RefusedError):
    """The orbit (errors included) cannot be run: names the first offending frame and axis."""

    def __init__(
        self, frame: int, axis: str, value: float | None, allowed: str, unit: str = "", note: str = ""
    ) -> None:
        self.frame = int(frame)
        self.axis = axis
        self.value = value
        self.allowed = allowed
        u = f" {unit}" if unit else ""
        what = f"axis {axis}" if value is None else f"axis {axis} = {value:.4g}{u}"
        super().__init__(
            f"orbit infeasible at frame {self.frame}: {what} is outside {allowed}; nothing moved"
            + (f". {note}" if note else "")
        )


class ScanAborted(AcquireError):
    """A scan ended before its last frame; ``reason`` says why."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


class ScanStateError(AcquireError):
    """An action that the scan's current state does not allow (e.g. resume when not paused)."""


class RepairError(AcquireError):
    """A scan file that cannot be repaired; the message says why."""


class StallError(AcquireError):
    """A device made no progress within its bound (``stall.*`` in the rig configuration); names the device."""

    def __init__(self, device: str, what: str, bound_s: float, setting: str) -> None:
        self.device = device
        self.bound_s = float(bound_s)
        super().__init__(f"stall: {device} {what} within {bound_s:g} s ({setting}); the scan stops safely")


class DiskSpaceError(AcquireError):
    """Too little free space for a scan (before it starts) or for its next frames (while it runs); gives the numbers."""
