"""Hexapod driver against the hexapod twin over loopback TCP: identify, refuse, reference, move, stop."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from devices.errors import (
    ControllerError,
    DeviceError,
    InterlockOpenError,
    NotReferencedError,
    OutOfLimitsError,
)
from devices.gcs.device import ServoOffError
from devices.gcs.errors import GcsOutOfLimitsError
from devices.hexapod import Hexapod
from devices.twins.runtime import TwinThread
from devices.twins.world import SimWorld

pytestmark = [pytest.mark.anyio, pytest.mark.system]


async def test_describe_and_read(hexapod: Hexapod) -> None:
    info = await hexapod.describe()
    assert info.model.startswith("C-887") and info.serial
    assert [a.name for a in info.axes] == ["X", "Y", "Z", "U", "V", "W"]
    assert [a.unit for a in info.axes] == ["mm"] * 3 + ["deg"] * 3
    assert (info.axes[0].low, info.axes[0].high) == (-50.0, 50.0)
    state = await hexapod.read()
    assert set(state) == {"position", "target", "on_target", "referenced", "servo", "moving"}
    assert not any(state["referenced"].values()) and not any(state["servo"].values())
    assert await hexapod.limits() == {
        "X": (-50, 50),
        "Y": (-50, 50),
        "Z": (-25, 25),
        "U": (-30, 30),
        "V": (-30, 30),
        "W": (-30, 30),
    }


async def test_refuses_to_move_with_servo_off_then_unreferenced(hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    before = await hexapod.position()
    with pytest.raises(ServoOffError, match="servo off"):
        await hexapod.move({"X": 1.0})
    await hexapod.servo(True)
    with pytest.raises(NotReferencedError, match="not referenced"):
        await hexapod.move({"X": 1.0})
    assert await hexapod.position() == pytest.approx(before, abs=1e-9)
    assert not hexapod_twin.twin.controller.is_moving()


async def test_reference_move_and_read_back(ready_hexapod: Hexapod, world: SimWorld) -> None:
    hexapod = ready_hexapod
    assert all((await hexapod.referenced()).values())
    reports = []
    status = hexapod.move({"X": 2.0, "Y": -1.0, "U": 1.5, "W": -2.0})
    status.watch(reports.append)
    await status
    assert status.success and reports and reports[-1].fraction == 1.0
    pos = await hexapod.position()
    assert pos["X"] == pytest.approx(2.0, abs=1e-3) and pos["U"] == pytest.approx(1.5, abs=1e-3)
    assert await hexapod.on_target() and not await hexapod.moving()
    # the true pose (what the detector sees) is close to, but not equal to, the read-back
    true = world.hexapod_true.copy()
    readback = np.array([pos[a] for a in "XYZ"] + [np.radians(pos[a]) for a in "UVW"])
    assert np.abs(true[:3] - readback[:3]).max() < 0.2
    assert np.abs(true - readback).max() > 1e-4


async def test_true_pose_sags_more_with_tilt(ready_hexapod: Hexapod, world: SimWorld) -> None:
    await ready_hexapod.move({"U": 0.0, "V": 0.0})
    z_flat = world.hexapod_true[2]
    await ready_hexapod.move({"U": 10.0})
    assert world.hexapod_true[2] < z_flat - 0.01
    assert np.degrees(world.hexapod_true[3]) < 10.0 - 0.01  # tilt droop


async def test_backlash_depends_on_direction(ready_hexapod: Hexapod, world: SimWorld) -> None:
    await ready_hexapod.move({"X": 5.0})
    await ready_hexapod.move({"X": 3.0})
    from_above = world.hexapod_true[0]
    await ready_hexapod.move({"X": 1.0})
    await ready_hexapod.move({"X": 3.0})
    from_below = world.hexapod_true[0]
    assert from_above - from_below == pytest.approx(0.004, abs=1e-6)


async def test_soft_limit_refused_before_anything_moves(ready_hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    sent = hexapod_twin.twin.controller.motion.target.copy()
    with pytest.raises(OutOfLimitsError, match=r"X=60 mm is outside the soft limits \[-50, 50\]"):
        await ready_hexapod.move({"X": 60.0, "Y": 1.0})
    with pytest.raises(OutOfLimitsError, match="finite"):
        await ready_hexapod.move({"Z": float("nan")})
    with pytest.raises(DeviceError, match="unknown axis 'Q'"):
        await ready_hexapod.move({"Q": 1.0})
    assert np.array_equal(hexapod_twin.twin.controller.motion.target, sent)


async def test_coupled_workspace_refused_with_vmo(ready_hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    corner = {"X": 50.0, "Y": 50.0, "U": 30.0, "V": 30.0}
    with pytest.raises(OutOfLimitsError, match="workspace"):
        await ready_hexapod.check_pose(corner)
    with pytest.raises(OutOfLimitsError, match="VMO"):
        await ready_hexapod.move(corner)
    assert not hexapod_twin.twin.controller.is_moving()
    assert await ready_hexapod.check_pose({"X": 50.0}) == {"X": 50.0}
    # the controller itself refuses the unreachable pose with error 7 if asked directly
    with pytest.raises(GcsOutOfLimitsError) as info:
        await ready_hexapod.client.command("MOV X 50 Y 50 U 30 V 30")
    assert info.value.code == 7


async def test_software_interlock_refuses_motion_until_it_clears(ready_hexapod: Hexapod) -> None:
    latched = ["emergency stop by test: smoke"]
    ready_hexapod.interlock = lambda: latched[0] if latched else None
    with pytest.raises(InterlockOpenError, match="move refused: emergency stop by test: smoke"):
        await ready_hexapod.move({"Z": 1.0})
    with pytest.raises(InterlockOpenError, match="referencing refused"):
        await ready_hexapod.reference()
    assert (await ready_hexapod.target())["Z"] == pytest.approx(0.0)  # nothing was commanded
    latched.clear()  # reset: it moves again
    await ready_hexapod.move({"Z": 1.0})
    assert (await ready_hexapod.position())["Z"] == pytest.approx(1.0, abs=0.01)


async def test_relative_move(ready_hexapod: Hexapod) -> None:
    await ready_hexapod.move({"Z": 1.0})
    await ready_hexapod.move_relative({"Z": 0.5})
    assert (await ready_hexapod.target())["Z"] == pytest.approx(1.5)
    with pytest.raises(OutOfLimitsError, match="Z=26.5"):
        await ready_hexapod.move_relative({"Z": 25.0})


async def test_stop_halts_running_move(ready_hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    await ready_hexapod.set_velocity(0.5)
    assert await ready_hexapod.velocity() == pytest.approx(0.5)
    for bad in (float("nan"), float("inf"), 0.0, -1.0):  # refused before anything is sent; the velocity stays
        with pytest.raises(OutOfLimitsError, match="must be a positive finite number; nothing changed"):
            await ready_hexapod.set_velocity(bad)
    assert await ready_hexapod.velocity() == pytest.approx(0.5)
    status = ready_hexapod.move({"X": 40.0})
    await asyncio.sleep(0.1)
    assert await ready_hexapod.moving()
    await ready_hexapod.stop()
    assert not hexapod_twin.twin.controller.is_moving()
    with pytest.raises(ControllerError) as info:
        await status
    assert info.value.code == 10
    x = (await ready_hexapod.position())["X"]
    assert 0.0 < x < 40.0


async def test_cancelling_a_move_halts_the_controller(ready_hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    await ready_hexapod.set_velocity(0.5)
    status = ready_hexapod.move({"Y": -40.0})
    await asyncio.sleep(0.1)
    status.cancel()
    with pytest.raises(asyncio.CancelledError):
        await status
    await asyncio.sleep(0.05)
    assert not hexapod_twin.twin.controller.is_moving()


async def test_pivot_point(ready_hexapod: Hexapod, world: SimWorld) -> None:
    await ready_hexapod.set_pivot(0.0, 0.0, 25.0)
    assert await ready_hexapod.pivot() == {"R": 0.0, "S": 0.0, "T": 25.0}
    await ready_hexapod.move({"V": 2.0})
    assert world.pivot_mm == (0.0, 0.0, 25.0)
    with pytest.raises(ControllerError) as info:
        await ready_hexapod.set_pivot(0.0, 0.0, 0.0)
    assert info.value.code == 9


@pytest.mark.parametrize(
    ("command", "code"),
    [
        ("XYZ 1", 2),
        ("MOV Q 1", 15),
        ("MOV X", 24),
        ("MOV X abc", 1),
        ("VLS 100", 17),
        ("SPI Q 1", 23),
    ],
)
async def test_controller_error_codes(ready_hexapod: Hexapod, command: str, code: int) -> None:
    with pytest.raises(ControllerError) as info:
        await ready_hexapod.client.command(command)
    assert info.value.code == code and info.value.command == command
    assert await ready_hexapod.client.error() == 0  # ERR? clears it


async def test_codes_93_89_while_moving_or_referencing(ready_hexapod: Hexapod) -> None:
    await ready_hexapod.set_velocity(0.5)
    status = ready_hexapod.move({"X": 20.0})
    await asyncio.sleep(0.05)
    with pytest.raises(ControllerError) as info:
        await ready_hexapod.client.command("SVO X 0")
    assert info.value.code == 93
    await ready_hexapod.stop()
    with pytest.raises(ControllerError):
        await status
    await ready_hexapod.client.command("FRF")
    assert not await ready_hexapod.ready()  # busy while referencing (#7)
    with pytest.raises(ControllerError) as info:
        await ready_hexapod.client.command("MOV X 1")
    assert info.value.code == 89
    await ready_hexapod.stop()


async def test_later_move_supersedes_a_running_one(ready_hexapod: Hexapod) -> None:
    await ready_hexapod.set_velocity(1.0)
    first = ready_hexapod.move({"X": 10.0})
    await asyncio.sleep(0.05)
    second = ready_hexapod.move({"X": 2.0})
    await second
    with pytest.raises(ControllerError, match="superseded") as info:
        await first
    assert info.value.code == 10
    assert (await ready_hexapod.position())["X"] == pytest.approx(2.0, abs=1e-3)


async def test_a_move_retargeted_past_its_time_limit_ends_superseded_and_never_halts(hexapod_twin: TwinThread) -> None:
    """Continuous mode retargets the hexapod frame by frame while it moves, so an early move may never see its axes
    on target: it must end as superseded at once, not wait out its time limit and halt the axes under the later
    moves (a continuous sawtooth scan aborted with "controller error 10 after 'MOV': Controller was stopped by
    command" in 2 of 4 runs)."""
    dev = Hexapod("hexapod", hexapod_twin.uri, timeout_s=1.0, move_timeout_s=0.5)
    await dev.connect()
    try:
        await dev.reference()
        await dev.set_velocity(0.01)  # 1 mm/s on this twin (100 times faster than real)
        moves, x = [], 0.0
        t0 = asyncio.get_running_loop().time()
        while asyncio.get_running_loop().time() - t0 < 1.0:  # twice the time limit; the target runs ahead at 1.2 mm/s
            x += 0.06
            moves.append(dev.move({"X": x}))
            await asyncio.sleep(0.05)
        await moves[-1]
        for early in moves[:-1]:
            with pytest.raises(ControllerError, match="superseded"):
                await early
        assert (await dev.position())["X"] == pytest.approx(x, abs=1e-3)
    finally:
        await dev.close()


async def test_cancelled_reference_halts(hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    status = hexapod.reference()
    await asyncio.sleep(0.002)
    while not hexapod_twin.twin.controller.referencing:
        await asyncio.sleep(0.001)
    status.cancel()
    with pytest.raises(asyncio.CancelledError):
        await status
    await asyncio.sleep(0.05)
    assert not hexapod_twin.twin.controller.is_moving() and not hexapod_twin.twin.controller.referencing
