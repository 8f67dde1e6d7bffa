"""The same hexapod driver over RS-232 (a pseudo-terminal served by the twin)."""

from __future__ import annotations

import pytest

from devices.errors import NotConnectedError, OutOfLimitsError
from devices.hexapod import Hexapod
from devices.twins.runtime import TwinThread

pytestmark = [pytest.mark.anyio, pytest.mark.system]


async def test_hexapod_over_serial(hexapod_twin: TwinThread) -> None:
    path = hexapod_twin.run_sync(hexapod_twin.twin.open_serial)
    dev = Hexapod("hexapod", f"serial://{path}?baud=115200", timeout_s=1.0)
    await dev.connect()
    try:
        await dev.reference()
        await dev.move({"X": 1.0, "W": 5.0})
        pos = await dev.position()
        assert pos["X"] == pytest.approx(1.0, abs=1e-3) and pos["W"] == pytest.approx(5.0, abs=1e-3)
        with pytest.raises(OutOfLimitsError, match="workspace"):
            await dev.move({"X": 50.0, "Y": 50.0, "U": 30.0, "V": 30.0})
        hexapod_twin.faults.garble_next = 1
        assert await dev.on_target()
    finally:
        await dev.close()


async def test_missing_serial_port_is_a_clear_error() -> None:
    dev = Hexapod("hexapod", "serial:///dev/does-not-exist?baud=115200")
    with pytest.raises(NotConnectedError, match="cannot open"):
        await dev.connect()
