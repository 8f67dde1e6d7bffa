"""Rotation-stage driver against its twin over loopback TCP and a pseudo-terminal (serial)."""

from __future__ import annotations

import math

import pytest

from devices.errors import OutOfLimitsError
from devices.gcs.device import ServoOffError
from devices.rotation_stage import RotationStage
from devices.twins.runtime import TwinThread
from devices.twins.world import SimWorld

pytestmark = [pytest.mark.anyio, pytest.mark.system]


async def test_describe_exposes_axis_r(stage: RotationStage) -> None:
    info = await stage.describe()
    assert [(a.name, a.unit, a.low, a.high) for a in info.axes] == [("R", "deg", -370.0, 370.0)]
    assert info.extra["axis_map"] == {"R": "1"}
    assert info.model.startswith("C-863")


async def test_refusals_then_reference_and_move(stage: RotationStage, world: SimWorld) -> None:
    with pytest.raises(ServoOffError) as refused:
        await stage.move({"R": 10.0})
    assert refused.value.axes == ("R",)
    with pytest.raises(OutOfLimitsError, match="R=371"):
        await stage.move({"R": 371.0})
    await stage.reference()
    assert await stage.referenced() == {"R": True}
    await stage.set_velocity(60.0)
    assert await stage.velocity() == 60.0
    with pytest.raises(OutOfLimitsError, match="velocity nan deg/s must be a positive finite number"):
        await stage.set_velocity(float("nan"))
    assert await stage.velocity() == 60.0
    await stage.move({"R": 120.0})
    pos = (await stage.position())["R"]
    assert pos == pytest.approx(120.0, abs=1e-3)
    true_deg = math.degrees(world.stage_true_rad)
    assert true_deg == pytest.approx(120.0, abs=0.1) and abs(true_deg - pos) > 1e-4
    await stage.move_relative({"R": -30.0})
    assert (await stage.target())["R"] == pytest.approx(90.0)


async def test_backlash_and_eccentricity_are_hidden(stage: RotationStage, world: SimWorld) -> None:
    await stage.reference()
    await stage.move({"R": 10.0})
    await stage.move({"R": 5.0})
    from_above = math.degrees(world.stage_true_rad)
    await stage.move({"R": 0.0})
    await stage.move({"R": 5.0})
    from_below = math.degrees(world.stage_true_rad)
    assert from_above - from_below == pytest.approx(0.003, abs=1e-6)
    assert abs((await stage.position())["R"] - 5.0) < 1e-3


async def test_drive_over_serial_pty(stage_twin: TwinThread) -> None:
    path = stage_twin.run_sync(stage_twin.twin.open_serial)
    dev = RotationStage("stage", f"serial://{path}?baud=115200", timeout_s=1.0)
    await dev.connect()
    try:
        await dev.reference()
        await dev.move({"R": -45.0})
        assert (await dev.position())["R"] == pytest.approx(-45.0, abs=1e-3)
        assert await dev.on_target() and await dev.ready()
        await dev.stop()
    finally:
        await dev.close()


async def test_other_axis_identifier(stage_twin: TwinThread) -> None:
    dev = RotationStage("stage", stage_twin.uri, axis="2")
    with pytest.raises(Exception, match="lacks"):
        await dev.connect()
    assert dev._client is None
