"""Injected faults against the real drivers: latency, dropped connection, garbled reply, controller error, stuck axis."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from devices.errors import (
    ControllerError,
    DeviceError,
    DeviceTimeoutError,
    NotConnectedError,
    OutOfLimitsError,
    ProtocolError,
)
from devices.hexapod import Hexapod
from devices.rotation_stage import RotationStage
from devices.twins.runtime import TwinThread

pytestmark = [pytest.mark.anyio, pytest.mark.system]


async def test_latency_within_timeout_is_tolerated(hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    hexapod_twin.faults.latency_s = 0.03
    t0 = time.monotonic()
    await hexapod.position()
    assert time.monotonic() - t0 >= 0.03
    assert hexapod.client.stats["retries"] == 0


async def test_latency_beyond_timeout_raises_after_one_retry(hexapod_twin: TwinThread) -> None:
    dev = Hexapod("slow", hexapod_twin.uri, timeout_s=0.05)
    await dev.connect()
    try:
        hexapod_twin.faults.latency_s = 0.2
        with pytest.raises(DeviceTimeoutError, match="2 attempts"):
            await dev.position()
        assert dev.client.stats["reconnects"] >= 1
        hexapod_twin.faults.latency_s = 0.0
        assert "X" in await dev.position()  # the driver recovers once the controller answers again
    finally:
        await dev.close()


async def test_dropped_connection_during_query_reconnects(hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    hexapod_twin.faults.drop_next = 1
    pos = await hexapod.position()
    assert set(pos) == set("XYZUVW")
    assert hexapod.client.stats["reconnects"] == 1
    hexapod_twin.call(hexapod_twin.twin.drop_connections)  # cable pulled between two commands
    assert await hexapod.on_target() in (True, False)
    assert hexapod.client.stats["reconnects"] == 2


async def test_dropped_connection_during_move_is_not_retried(ready_hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    hexapod_twin.faults.match = "MOV "  # the move command, not the MOV? query before it
    hexapod_twin.faults.drop_next, hexapod_twin.faults.drop_executes = 1, False
    with pytest.raises(NotConnectedError, match="may or may not have run"):
        await ready_hexapod.move({"X": 3.0})
    assert hexapod_twin.twin.controller.motion.target[0] == 0.0  # lost before the controller ran it: nothing moved
    hexapod_twin.faults.drop_next, hexapod_twin.faults.drop_executes = 1, True
    with pytest.raises(NotConnectedError, match="not repeated"):
        await ready_hexapod.move({"X": 3.0})
    assert hexapod_twin.twin.controller.motion.target[0] == 3.0  # it ran exactly once; the driver did not resend
    commands = ready_hexapod.client.stats["commands"]
    await ready_hexapod.move({"X": 4.0})  # the next move reconnects and works
    assert ready_hexapod.client.stats["commands"] == commands + 1


async def test_garbled_reply_is_retried_then_reported(hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    hexapod_twin.faults.garble_next = 1
    assert set(await hexapod.position()) == set("XYZUVW")
    assert hexapod.client.stats["retries"] == 1
    hexapod_twin.faults.garble_next = 2
    with pytest.raises(ProtocolError, match="POS"):
        await hexapod.position()


async def test_garbled_err_reply_after_move_is_not_retried(ready_hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    target = ready_hexapod.client
    ready_hexapod.check_limits({"Y": 2.0})
    await ready_hexapod.check_pose({"Y": 2.0})
    hexapod_twin.faults.garble_next = 1
    with pytest.raises(ProtocolError, match="may or may not have run"):
        await target.command("MOV Y 2")
    assert hexapod_twin.twin.controller.motion.target[1] == 2.0


async def test_injected_controller_errors(ready_hexapod: Hexapod, hexapod_twin: TwinThread) -> None:
    hexapod_twin.faults.add_error(17, "MOV")
    with pytest.raises(ControllerError) as info:
        await ready_hexapod.move({"Z": 1.0})
    assert info.value.code == 17 and "Parameter out of range" in str(info.value)
    hexapod_twin.faults.add_error(7, "MOV")
    with pytest.raises(OutOfLimitsError):
        await ready_hexapod.move({"Z": 1.0})
    assert hexapod_twin.twin.controller.motion.target[2] == 0.0
    await ready_hexapod.move({"Z": 1.0})


async def test_stuck_axis_times_out_and_halts(hexapod_twin: TwinThread) -> None:
    dev = Hexapod("hexapod", hexapod_twin.uri, move_timeout_s=0.3)
    await dev.connect()
    try:
        await dev.reference()
        hexapod_twin.twin.controller.stick("Y")
        with pytest.raises(DeviceTimeoutError, match="Y not on target"):
            await dev.move({"X": 1.0, "Y": 1.0})
        assert not hexapod_twin.twin.controller.is_moving()
        assert not await dev.moving()
    finally:
        await dev.close()


async def test_serial_faults_and_refusals(stage_twin: TwinThread) -> None:
    path = stage_twin.run_sync(stage_twin.twin.open_serial)
    dev = RotationStage("stage", f"serial://{path}?baud=115200", timeout_s=0.3, move_timeout_s=5.0)
    await dev.connect()
    try:
        assert (await dev.describe()).model.startswith("C-863")
        await dev.servo(True)
        with pytest.raises(Exception, match="not referenced"):
            await dev.move({"R": 10.0})
        await dev.reference()
        stage_twin.faults.garble_next = 1
        assert "R" in await dev.position()
        stage_twin.faults.latency_s = 0.02
        await dev.move({"R": 45.0})
        stage_twin.faults.latency_s = 0.0
        assert (await dev.position())["R"] == pytest.approx(45.0, abs=1e-3)
        stage_twin.faults.drop_next = 1  # a serial line loses the reply: timeout, then the retry answers
        assert "R" in await dev.position()
        stage_twin.faults.add_error(5, "MOV")
        with pytest.raises(ControllerError) as info:
            await dev.move({"R": 10.0})
        assert info.value.code == 5
        with pytest.raises(OutOfLimitsError, match=r"\[-370, 370\]"):
            await dev.move({"R": 400.0})
        stage_twin.twin.controller.stick("1")
        dev.move_timeout_s = 0.3
        with pytest.raises(DeviceTimeoutError, match="R not on target"):
            await dev.move({"R": 50.0})
        assert np.isclose((await dev.target())["R"], (await dev.position())["R"], atol=1e-3)
    finally:
        await dev.close()


async def test_stop_reaches_the_controller_after_a_silent_disconnect(
    ready_hexapod: Hexapod, hexapod_twin: TwinThread
) -> None:
    await ready_hexapod.set_velocity(0.5)
    status = ready_hexapod.move({"Z": 20.0})
    await asyncio.sleep(0.1)
    hexapod_twin.call(hexapod_twin.twin.drop_connections)  # the driver has not noticed yet
    await asyncio.sleep(0.02)
    await ready_hexapod.stop()
    assert not hexapod_twin.twin.controller.is_moving()
    assert ready_hexapod.client.stats["reconnects"] >= 1
    with pytest.raises(DeviceError):
        await status


async def test_a_stop_while_a_query_reconnects_waits_for_the_new_connection(
    ready_hexapod: Hexapod, hexapod_twin: TwinThread
) -> None:
    """A poll finds the connection dropped and opens a new one (slowly: a loaded machine, a slow network); a stop in
    that moment is sent over the new connection, never refused as 'not connected'."""
    client = ready_hexapod.client
    await ready_hexapod.set_velocity(0.5)
    status = ready_hexapod.move({"Z": 20.0})
    await asyncio.sleep(0.1)
    opened = client.connect

    async def slow_connect() -> None:
        await asyncio.sleep(0.3)
        await opened()

    client.connect = slow_connect  # type: ignore[method-assign]
    hexapod_twin.call(hexapod_twin.twin.drop_connections)
    poll = asyncio.ensure_future(client.query("POS?"))
    for _ in range(200):  # until the poll has closed the dead connection and is opening a new one
        if not client.connected:
            break
        await asyncio.sleep(0.005)
    assert not client.connected
    await ready_hexapod.stop()
    assert not hexapod_twin.twin.controller.is_moving()
    await poll
    with pytest.raises(DeviceError):
        await status


async def test_serial_resynchronises_after_late_replies(stage_twin: TwinThread) -> None:
    path = stage_twin.run_sync(stage_twin.twin.open_serial)
    dev = RotationStage("stage", f"serial://{path}?baud=115200", timeout_s=0.1)
    await dev.connect()
    try:
        stage_twin.faults.latency_s = 0.15
        with pytest.raises(DeviceTimeoutError):
            await dev.position()
        stage_twin.faults.latency_s = 0.0
        assert await dev.velocity() == pytest.approx(30.0)  # not a late POS? reply
        assert set(await dev.limits(refresh=True)) == {"R"}
    finally:
        await dev.close()
