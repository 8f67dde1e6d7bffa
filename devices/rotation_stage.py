"""Rotation-stage driver (one rotary axis on a GCS 2.0 controller), exposed as axis 'R' in degrees.

The controller calls the axis '1' (as PI's single-axis controllers do); the
driver maps it to 'R' at its edge (pass ``axis='...'`` for another identifier).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from devices.gcs.device import GcsMotionDevice
from devices.gcs.framing import format_command, parse_axis_values


class RotationStage(GcsMotionDevice):
    """A rotation stage: axis 'R' (deg), controller axis '1' by default."""

    kind: ClassVar[str] = "rotation_stage"
    units: ClassVar[dict[str, str]] = {"R": "deg"}

    def __init__(self, name: str, uri: str, *, axis: str = "1", **options: Any) -> None:
        super().__init__(name, uri, **options)
        self.axis_map = {"R": str(axis)}  # type: ignore[misc]
        self._velocity: float | None = None

    async def velocity(self) -> float:
        """Axis velocity (``VEL?``) in deg/s."""
        values = await self.client.query(f"VEL? {self.axis_map['R']}", lambda lines: parse_axis_values(lines, "VEL?"))
        self._velocity = float(values[self.axis_map["R"]])
        return self._velocity

    async def set_velocity(self, deg_per_s: float) -> None:
        """Set the axis velocity (``VEL``)."""
        v = self.check_velocity(deg_per_s, "deg/s")
        await self.client.command(format_command("VEL", {self.axis_map["R"]: v}))
        self._velocity = v

    def _estimate_s(self, start: Mapping[str, float], targets: Mapping[str, float]) -> float:
        return abs(targets["R"] - start["R"]) / (self._velocity or 1.0) + 1.0

    async def connect(self) -> None:
        await super().connect()
        await self.velocity()
