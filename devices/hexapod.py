"""Hexapod driver (PI C-887 style, GCS 2.0): axes X, Y, Z (mm) and U, V, W (deg) about a pivot point.

U, V, W follow PI's convention ``R = R_x(U) R_y(V) R_z(W)`` applied about the
pivot point (``SPI`` R, S, T in mm), as ``orbitct.kinematics`` models it. The
workspace is coupled, so every move is first checked axis by axis against
TMN?/TMX? and then as a full pose with ``VMO?``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from devices.errors import OutOfLimitsError, ProtocolError
from devices.gcs.device import GcsMotionDevice
from devices.gcs.framing import format_command, parse_axis_values

AXES = ("X", "Y", "Z", "U", "V", "W")


class Hexapod(GcsMotionDevice):
    """A six-axis hexapod on a GCS 2.0 controller."""

    kind: ClassVar[str] = "hexapod"
    axis_map: ClassVar[dict[str, str]] = {a: a for a in AXES}
    units: ClassVar[dict[str, str]] = {"X": "mm", "Y": "mm", "Z": "mm", "U": "deg", "V": "deg", "W": "deg"}

    def __init__(self, name: str, uri: str, **options: Any) -> None:
        super().__init__(name, uri, **options)
        self._velocity: float | None = None

    async def check_pose(
        self, targets: Mapping[str, float], current: Mapping[str, float] | None = None
    ) -> dict[str, float]:
        """Check a (partial) target pose: soft limits per axis, then ``VMO?`` on the full pose.

        Axes not given keep their present targets (``current``, else read with ``MOV?``).
        """
        checked = self.check_limits(targets)
        full = dict(current) if current is not None else await self.target()
        full.update(checked)
        reachable = await self.client.query(format_command("VMO?", full), _parse_flag)
        if not reachable:
            pose = ", ".join(f"{k}={v:g}" for k, v in full.items())
            raise OutOfLimitsError(
                f"{self.name}: pose {pose} (mm, deg) is outside the hexapod's workspace (VMO? = 0), "
                f"though each axis is within its soft limits; nothing moved"
            )
        return checked

    async def velocity(self) -> float:
        """System velocity (``VLS?``) in mm/s (deg/s for U, V, W)."""
        self._velocity = await self.client.query("VLS?", lambda lines: _parse_float(lines, "VLS?"))
        return float(self._velocity)

    async def set_velocity(self, mm_per_s: float) -> None:
        """Set the system velocity (``VLS``)."""
        v = self.check_velocity(mm_per_s, "mm/s")
        await self.client.command(f"VLS {v:.6f}")
        self._velocity = v

    async def pivot(self) -> dict[str, float]:
        """Pivot point R, S, T (``SPI?``) in mm."""
        return await self.client.query("SPI? R S T", lambda lines: parse_axis_values(lines, "SPI?"))

    async def set_pivot(self, r_mm: float, s_mm: float, t_mm: float) -> None:
        """Set the pivot point (``SPI``; allowed only while U, V and W are 0)."""
        await self.client.command(format_command("SPI", {"R": r_mm, "S": s_mm, "T": t_mm}))

    def _estimate_s(self, start: Mapping[str, float], targets: Mapping[str, float]) -> float:
        v = self._velocity or 1.0
        return max(abs(targets[k] - start[k]) for k in targets) / v + 1.0

    async def connect(self) -> None:
        await super().connect()
        await self.velocity()


def _parse_flag(lines: list[str]) -> bool:
    if lines and lines[0].strip() in ("0", "1"):
        return lines[0].strip() == "1"
    raise ProtocolError(f"unreadable VMO? reply {lines!r}")


def _parse_float(lines: list[str], command: str) -> float:
    try:
        return float(lines[0].strip())
    except (ValueError, IndexError):
        raise ProtocolError(f"unreadable {command} reply {lines!r}") from None
