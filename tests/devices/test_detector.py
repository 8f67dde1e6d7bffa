"""Detector driver against the detector twin over loopback TCP: frames, triggers, dark/flat, binning, faults."""

from __future__ import annotations

import asyncio
import itertools
import logging
import socket
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np
import pytest

from devices.detector import Detector, Frame
from devices.errors import (
    ControllerError,
    DeviceTimeoutError,
    NotConnectedError,
    ProtocolError,
    UriError,
)
from devices.factory import open_device, opened
from devices.sim import twin_of
from devices.twins.detector import DetectorTwin
from devices.twins.runtime import TwinThread
from devices.twins.world import get_world, reset_world
from orbitct.geometry import ViewGeometry
from orbitct.kinematics import object_pose

pytestmark = [pytest.mark.timeout(120), pytest.mark.system]
_worlds = itertools.count()


def run(body: Callable[[Detector], Awaitable[Any]], **options: Any) -> Any:
    """A fresh world and a sim:// detector (64 px), ``body(det)``, close."""
    world = f"dettest{next(_worlds)}"
    reset_world(world)
    options.setdefault("rows", 64)
    options.setdefault("timeout_s", 1.0)

    async def main() -> Any:
        async with opened("detector", "detector", f"sim://{world}", **options) as det:
            return await body(det)

    return asyncio.run(main())


def test_software_trigger_frame_at_true_pose() -> None:
    async def body(det: Detector) -> tuple[Frame, Frame, str]:
        assert det.shape == (64, 64) and det.geometry.pitch_col == pytest.approx(427 / 64)
        await det.arm()
        first = await det.trigger()
        with twin_of(det).world.lock:
            twin_of(det).world.stage_true_rad = np.radians(30.0)
        second = await det.trigger()
        return first, second, twin_of(det).world.name

    first, second, world = run(body)
    assert first.data.dtype == np.uint16 and first.shape == (64, 64) and first.kind == "projection"
    assert (first.number, second.number) == (1, 2) and second.timestamp >= first.timestamp
    assert first.meta["kv"] == 90.0 and first.meta["exposure_ms"] == 10.0
    # the object attenuates: the projection is darker than the open field somewhere
    assert first.data.min() < 0.8 * np.percentile(first.data, 99)
    assert not np.array_equal(first.data, second.data)
    # the recorded true view is the fixed lab view seen from the world's true object pose
    w = get_world(world)
    R, t = object_pose(np.radians(30.0), np.zeros(6), order=w.stack_order, pivot=w.pivot_mm)
    lab = ViewGeometry.from_carm(0.0, 0.0, 785.0, 1200.0, DetectorTwin(rows=64).geometry)
    expected = ViewGeometry.from_object_poses(lab, R, t).vectors[0]
    np.testing.assert_allclose(second.meta["truth_vectors"], expected, atol=1e-9)


def test_dark_flat_and_dose_scaling() -> None:
    async def body(det: Detector) -> tuple[list[Frame], list[Frame], list[Frame]]:
        darks = await det.acquire_dark(2)
        flats = await det.acquire_flat(2)
        with twin_of(det).world.lock:
            twin_of(det).world.xray_ma = 2.0
        bright = await det.acquire_flat(1)
        return darks, flats, bright

    darks, flats, bright = run(body)
    assert [f.kind for f in darks + flats] == ["dark", "dark", "flat", "flat"]
    assert [f.number for f in darks + flats] == [1, 2, 3, 4]
    assert abs(darks[0].data.mean() - 300) < 20
    assert flats[0].data.mean() > 10 * darks[0].data.mean()
    assert bright[0].data.mean() == pytest.approx(2 * flats[0].data.mean() - darks[0].data.mean(), rel=0.05)


def test_explicit_pitch() -> None:
    async def body(det: Detector) -> None:
        assert det.geometry.pitch_mm == (0.5, 0.25)

    run(body, pitch_mm="0.5,0.25")
    run(lambda det: _check_pitch(det, 0.556), pitch_mm=0.556)


async def _check_pitch(det: Detector, pitch: float) -> None:
    assert det.geometry.pitch_mm == (pitch, pitch)


def test_binning_changes_shape_and_pitch() -> None:
    async def body(det: Detector) -> Frame:
        await det.set_binning(2)
        assert det.shape == (32, 32) and det.geometry.pitch_col == pytest.approx(2 * 427 / 64)
        with pytest.raises(ControllerError, match="binning must be"):
            await det.set_binning(3)
        await det.arm()
        return await det.trigger()

    assert run(body).shape == (32, 32)


def test_generator_exposure_triggers_frame() -> None:
    world = f"dettest{next(_worlds)}"
    reset_world(world)

    async def main() -> None:
        async with (
            opened("detector", "det", f"sim://{world}", rows=64, trigger="xray") as det,
            opened("xray", "xray", f"sim://{world}", prep_s=0.01, heartbeat_s=0) as gen,
        ):
            await det.arm()
            with pytest.raises(ControllerError) as err:  # no software trigger in XRAY mode
                await det.trigger()
            assert err.value.code == 2
            await gen.configure(80, 2.0, 5)
            for expected in (1, 2):
                assert await gen.expose() == expected
                frame = await det.read_frame(timeout_s=5.0)
                assert frame.kind == "projection" and frame.meta["kv"] == 80.0 and frame.meta["ma"] == 2.0
            with pytest.raises(DeviceTimeoutError, match="no frame"):  # no exposure, no frame
                await det.read_frame(timeout_s=0.1)
            twin_of(det).faults.missing_frame_next = 1
            assert await gen.expose() == 3
            with pytest.raises(DeviceTimeoutError, match="no frame"):
                await det.read_frame(timeout_s=0.5)
            assert await gen.expose() == 4
            with pytest.raises(DeviceTimeoutError, match=r"frame\(s\) 3 missing \(received frame 4\)"):
                await det.read_frame(timeout_s=5.0)

    asyncio.run(main())


def test_not_armed_refuses_software_trigger() -> None:
    async def body(det: Detector) -> None:
        await det.disarm()
        with pytest.raises(ControllerError, match="armed"):
            await det.trigger()

    run(body)


def test_faults_latency_drop_garble_error_missing() -> None:
    async def body(det: Detector) -> None:
        faults = twin_of(det).faults
        await det.arm()
        faults.latency_s = 0.5
        with pytest.raises(DeviceTimeoutError, match="no reply"):
            await det.read()
        faults.latency_s = 0.0
        await asyncio.sleep(0.6)
        assert (await det.read())["armed"] == 1  # reconnected, in step again

        faults.drop_next = 1
        assert (await det.read())["mode"] == "SOFTWARE"  # safe query: reconnect and repeat once

        faults.match, faults.drop_next = "TRIG", 1
        with pytest.raises(NotConnectedError):
            await det.trigger()  # a trigger is never repeated
        assert "TRIG" in twin_of(det).commands_seen and twin_of(det).commands_seen.count("TRIG") == 1
        faults.match = ""

        faults.garble_next = 1
        with pytest.raises(ProtocolError, match="garbled"):
            await det._l().command("STATE?", retry=False)

        faults.error_next = 1
        with pytest.raises(ControllerError) as err:
            await det.read()
        assert err.value.code == 5 and "injected" in err.value.text

        frame = await det.trigger()
        faults.missing_frame_next = 1
        with pytest.raises(DeviceTimeoutError, match=f"frame {frame.number + 1} missing.*not re-triggered"):
            await det.trigger()  # its frame never arrives
        assert twin_of(det).commands_seen.count("TRIG") == 3
        assert (await det.trigger()).number == frame.number + 2  # reported once, not again as a gap

    run(body, timeout_s=0.3, frame_timeout_s=1.0)


def test_garbled_frame_header_is_a_protocol_error() -> None:
    async def body(det: Detector) -> None:
        await det.arm()
        twin_of(det).faults.match, twin_of(det).faults.garble_next = "FRAME?", 1
        with pytest.raises(ProtocolError):
            await det.trigger()

    run(body)


def test_standalone_twin_over_tcp() -> None:
    reset_world("dettcp")
    twin = DetectorTwin(get_world("dettcp"), rows=32)
    thread = TwinThread(twin)
    try:

        async def main() -> None:
            async with Detector("det", f"tcp://127.0.0.1:{thread.port}", timeout_s=2.0) as det:
                info = await det.describe()
                assert info.model == "orbitct SimPanel" and info.extra["rows"] == 32
                await det.arm()
                assert (await det.trigger()).shape == (32, 32)

        asyncio.run(main())
    finally:
        thread.stop()


def test_twin_stopped_while_a_frame_is_awaited_closes_quietly(caplog: pytest.LogCaptureFixture) -> None:
    """A twin stopped while a request waits ends the link; asyncio logs no 'Exception in callback' traceback."""
    reset_world("detstop")
    thread = TwinThread(DetectorTwin(get_world("detstop"), rows=8))
    with socket.create_connection(("127.0.0.1", thread.port), timeout=5.0) as link:
        link.sendall(b"ARM\nFRAME? 10000\n")
        assert link.recv(64).startswith(b"OK")  # ARM's reply; FRAME? waits for an exposure that never comes
        time.sleep(0.2)
        with caplog.at_level(logging.ERROR):
            thread.stop()
        assert link.recv(64) == b""  # closed
    assert not [r for r in caplog.records if "Exception in callback" in r.getMessage()], caplog.text


def test_bad_options() -> None:
    async def main() -> None:
        with pytest.raises(UriError, match="allowed"):
            await open_device("detector", "d", "sim://bench", colour=1)
        with pytest.raises(UriError, match="trigger"):
            await open_device("detector", "d", "sim://bench", trigger="foot")

    asyncio.run(main())
    with pytest.raises(UriError, match="tcp://"):
        Detector("d", "serial:///dev/ttyUSB0")
    with pytest.raises(UriError, match="tcp://"):  # the driver never sees sim://: devices.sim resolves it
        Detector("d", "sim://bench")


def test_unreachable_detector() -> None:
    async def main() -> None:
        with pytest.raises(NotConnectedError, match="cannot connect"):
            await Detector("d", "tcp://127.0.0.1:1", timeout_s=0.3).connect()

    asyncio.run(main())


def test_cancelled_read_leaves_the_link_usable() -> None:
    async def body(det: Detector) -> None:
        await det.arm()
        twin_of(det).faults.latency_s = 0.3
        task = asyncio.ensure_future(det.read())
        await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        twin_of(det).faults.latency_s = 0.0
        assert (await det.read())["armed"] == 1  # no stale reply read as this one's

    run(body)


def test_render_failure_is_reported_as_device_error() -> None:
    async def body(det: Detector) -> None:
        await det.arm()
        twin_of(det).set_phantom("Z")  # no such experiment phantom
        with pytest.raises(ControllerError, match="frame 1 could not be rendered.*unknown experiment"):
            await det.trigger()
        twin_of(det).set_phantom("A")
        assert (await det.trigger()).number == 2

    run(body)
