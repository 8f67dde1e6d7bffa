"""open_device by kind and URI, and stop_all halting a whole bench at once."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from devices.carm import CArm
from devices.detector import Detector
from devices.errors import DeviceError, UriError
from devices.factory import DRIVERS, device_class, open_device, stop_all
from devices.folder_detector import FolderWatchDetector
from devices.hexapod import Hexapod
from devices.rotation_stage import RotationStage
from devices.sim import stop_twins, twin_of
from devices.twins.runtime import TwinThread
from devices.xray import XrayGenerator

pytestmark = [pytest.mark.anyio, pytest.mark.system]


def test_driver_follows_kind_and_scheme() -> None:
    assert set(DRIVERS) == {"hexapod", "rotation_stage", "xray", "detector", "carm"}
    assert device_class("rotation-stage") is RotationStage
    assert device_class("hexapod", "serial") is Hexapod
    assert device_class("detector", "tcp") is Detector and device_class("detector", "folder") is FolderWatchDetector
    assert device_class("xray", "modbus") is XrayGenerator and device_class("carm") is CArm
    with pytest.raises(DeviceError, match="kinds are"):
        device_class("laser")
    with pytest.raises(UriError, match="connects by"):
        device_class("hexapod", "folder")


async def test_open_by_uri(hexapod_twin: TwinThread, stage_twin: TwinThread) -> None:
    hexa = await open_device("hexapod", "hexapod", hexapod_twin.uri)
    stage = await open_device("rotation_stage", "stage", f"tcp://127.0.0.1:{stage_twin.port}")
    try:
        assert isinstance(hexa, Hexapod) and (await hexa.describe()).model.startswith("C-887")
        assert (await stage.limits())["R"] == (-370.0, 370.0)
    finally:
        await hexa.close()
        await stage.close()
    with pytest.raises(UriError):
        await open_device("hexapod", "hexapod", "ftp://somewhere")
    with pytest.raises(DeviceError, match=r"unknown option\(s\) timeout;"):
        await open_device("hexapod", "hexapod", hexapod_twin.uri, timeout=1.0)
    with pytest.raises(DeviceError, match="speed"):
        await open_device("hexapod", "hexapod", "sim://factory-test?speed=9")
    for uri in (
        "tcp://127.0.0.1:1?connect_timeout=nan",
        "modbus://127.0.0.1:1?timeout_s=inf",
    ):  # refused before connecting
        with pytest.raises(UriError, match="is not a finite number"):
            await open_device("xray" if uri.startswith("modbus") else "hexapod", "x", uri)
    with pytest.raises(DeviceError, match="cannot connect"):
        await open_device("hexapod", "hexapod", "tcp://127.0.0.1:1")


async def test_sim_uri_starts_in_process_twin_on_loopback() -> None:
    try:
        hexa = await open_device("hexapod", "hexapod", "sim://factory-test?time_scale=50")
        try:
            assert twin_of(hexa).connections >= 1 and hexa.uri.startswith("tcp://127.0.0.1:")  # the driver saw loopback
            assert hexa.client.endpoint.scheme == "tcp" and hexa.client.endpoint.host == "127.0.0.1"
            await hexa.reference()
            await hexa.move({"Z": 2.0})
            from devices.twins.world import get_world

            assert get_world("factory-test").hexapod_true[2] == pytest.approx(2.0, abs=0.2)
        finally:
            await hexa.close()
    finally:
        stop_twins()


class _XrayOffRecorder:
    """Stands in for the X-ray generator's stop surface only (its driver is tested elsewhere)."""

    def __init__(self) -> None:
        self.off = 0

    async def xray_off(self) -> None:
        self.off += 1


class _Broken:
    async def stop(self) -> None:
        raise DeviceError("broken: cannot stop")


async def test_stop_all_halts_everything_concurrently(hexapod_twin: TwinThread, stage_twin: TwinThread) -> None:
    hexa = await open_device("hexapod", "hexapod", hexapod_twin.uri)
    stage = await open_device("rotation_stage", "stage", stage_twin.uri)
    xray = _XrayOffRecorder()
    try:
        await asyncio.gather(hexa.reference(), stage.reference())
        await hexa.set_velocity(0.5)
        await stage.set_velocity(1.0)
        moves = [hexa.move({"X": 30.0}), stage.move({"R": 300.0})]
        await asyncio.sleep(0.1)
        assert hexapod_twin.twin.controller.is_moving() and stage_twin.twin.controller.is_moving()
        errors = await stop_all([hexa, stage, xray, _Broken()])
        assert not hexapod_twin.twin.controller.is_moving() and not stage_twin.twin.controller.is_moving()
        assert xray.off == 1
        assert len(errors) == 1 and "broken" in str(errors[0])
        results: list[Any] = await asyncio.gather(*moves, return_exceptions=True)
        assert all(getattr(r, "code", None) == 10 for r in results)
    finally:
        await hexa.close()
        await stage.close()
