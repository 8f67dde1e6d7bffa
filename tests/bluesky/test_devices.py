"""The ophyd-async devices on their own: read and move on the twins, and ophyd-async's mock mode without any."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from bluesky import RunEngine
from bluesky import plan_stubs as bps
from bluesky.run_engine import call_in_bluesky_event_loop

from acquire.config import BenchConfig
from orbitct.scanfile import ImageKey
from orbitct_bluesky import Bench, FlatPanel, Hexapod, RotationStage, XrayGenerator
from tests.helpers.bench import small_config


def test_devices_read_and_move_on_the_twins(RE: RunEngine, open_bench: Callable[[BenchConfig], Bench]) -> None:
    bench = open_bench(small_config(size=32))

    async def ready() -> None:  # the twins start as real controllers do: not referenced, servo off
        for driver in (bench.stage.driver, bench.hexapod.driver):
            await driver.reference()
            await driver.servo(True)

    call_in_bluesky_event_loop(ready())
    RE(bps.mv(bench.stage, 30.0, bench.hexapod, {"X": 1.5, "U": 0.5}))
    reading = call_in_bluesky_event_loop(bench.stage.read())
    assert abs(reading["stage-R"]["value"] - 30.0) < 0.01
    located = call_in_bluesky_event_loop(bench.hexapod.locate())
    assert located["setpoint"]["X"] == 1.5 and abs(located["readback"]["U"] - 0.5) < 0.01
    assert sorted(bench.hexapod.hints["fields"]) == sorted(f"hexapod-{a}" for a in "XYZUVW")
    with pytest.raises(ValueError, match="no axis Q; its axes are X, Y, Z, U, V, W"):
        call_in_bluesky_event_loop(_set(bench.hexapod, {"Q": 1.0}))


async def _set(device: Hexapod, value: dict[str, float]) -> None:
    await device.set(value)


def test_mock_mode_has_no_driver_moves_at_once_and_gives_dark_frames(RE: RunEngine) -> None:
    hexapod, stage = Hexapod("tcp://192.0.2.1:50000", "hexapod"), RotationStage("tcp://192.0.2.1:50001", "stage")
    xray = XrayGenerator("modbus://192.0.2.1:502", "xray")
    panel = FlatPanel("tcp://192.0.2.1:7000", "panel", rows=8, cols=6)

    async def connect() -> None:
        for device in (hexapod, stage, xray, panel):
            await device.connect(mock=True)

    call_in_bluesky_event_loop(connect())  # nothing listens at 192.0.2.1 (TEST-NET-1): no driver is opened
    RE(bps.mv(stage, 45.0, hexapod, {"Z": -2.0}))
    assert call_in_bluesky_event_loop(stage.R.get_value()) == 45.0
    assert call_in_bluesky_event_loop(hexapod.Z.get_value()) == -2.0
    RE(bps.mv(xray, {"kv": 90.0, "ma": 1.0, "exposure_ms": 10.0}, panel.image_key, int(ImageKey.DARK)))
    RE(bps.trigger(xray, wait=True))
    RE(bps.trigger(panel, wait=True))
    assert call_in_bluesky_event_loop(xray.frame_counter.get_value()) == 1
    image = call_in_bluesky_event_loop(panel.image.get_value())
    assert image.shape == (8, 6) and not np.any(image)
    with pytest.raises(RuntimeError, match="mock mode: there is no driver"):
        _ = stage.driver
