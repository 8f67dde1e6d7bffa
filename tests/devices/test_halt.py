"""Emergency halt with proof: every device stopped at once and read back; anything unproven is named."""

from __future__ import annotations

import asyncio

import pytest

from devices.halt import halt_and_verify, summary
from devices.hexapod import Hexapod
from devices.rotation_stage import RotationStage
from devices.twins.runtime import TwinThread
from devices.twins.world import SimWorld
from devices.twins.xray import XrayTwin
from devices.xray import XrayGenerator

pytestmark = [pytest.mark.anyio, pytest.mark.system, pytest.mark.timeout(60)]


@pytest.fixture
async def xray(world: SimWorld):  # type: ignore[no-untyped-def]
    twin = TwinThread(XrayTwin(world, prep_s=0.02))
    gen = XrayGenerator("xray", twin.uri, heartbeat_s=0, timeout_s=0.3)
    await gen.connect()
    yield gen, twin
    await gen.close()
    twin.stop()


async def test_halt_stops_moving_axes_and_high_voltage_and_proves_it(
    ready_hexapod: Hexapod, stage: RotationStage, xray
) -> None:  # type: ignore[no-untyped-def]
    gen, twin = xray
    await stage.reference()
    await gen.prepare()
    assert twin.twin.state.name == "READY"
    moves = [stage.move({"R": 300.0}), ready_hexapod.move({"Z": 20.0})]
    await asyncio.sleep(0.05)
    checks = await halt_and_verify([ready_hexapod, stage, gen], timeout_s=1.0)
    assert [c.device for c in checks] == ["hexapod", "stage", "xray"]
    assert all(c.halted and not c.problem for c in checks), checks
    assert "not moving" in checks[0].verified and "high voltage off" in checks[2].verified
    ok, line = summary(checks)
    assert ok and line.startswith("halted and verified")
    assert twin.twin.state.name == "IDLE"
    await asyncio.gather(*(asyncio.wait_for(asyncio.shield(asyncio.ensure_future(_settled(m))), 5) for m in moves))


async def _settled(status) -> None:  # type: ignore[no-untyped-def]
    try:
        await status
    except Exception:  # noqa: BLE001 - a move cut short ends with the controller's "stopped" error
        pass


async def test_garbled_or_missing_confirmation_is_not_halted(xray) -> None:  # type: ignore[no-untyped-def]
    gen, twin = xray
    twin.twin.faults.garble_next = (
        1  # one garbled reply: the driver repeats the (idempotent) X-rays-off on a fresh link
    )
    (check,) = await halt_and_verify([gen], timeout_s=1.0)
    assert check.halted, check
    twin.twin.faults.garble_next = 3  # the repeat garbled too: not proven
    (check,) = await halt_and_verify([gen], timeout_s=1.0)
    assert not check.halted and "garbled" in check.problem, check
    ok, line = summary([check])
    assert not ok and line.startswith("NOT verified: xray: stop not acknowledged (garbled")

    twin.twin.faults.latency_s = 2.0  # no reply at all within the bound
    (check,) = await halt_and_verify([gen], timeout_s=0.5)
    twin.twin.faults.latency_s = 0.0
    assert not check.halted and "no reply" in check.problem and "read-back failed" in check.problem, check


async def test_nothing_to_halt_is_not_a_success() -> None:
    ok, line = summary(await halt_and_verify([object()]))
    assert not ok and "no device" in line


class _Regenerating:
    """A generator that something else switches back on once right after the stop (a scan's next frame)."""

    name = "xray"

    def __init__(self, on_after_stop: int) -> None:
        self.on_after_stop, self.offs = on_after_stop, 0

    async def xray_off(self) -> None:
        self.offs += 1

    async def read(self) -> dict[str, object]:
        on = self.offs <= self.on_after_stop
        return {"hv_on": on, "exposing": False, "state": "READY" if on else "IDLE"}


async def test_high_voltage_switched_on_again_after_the_stop_is_stopped_again_and_said() -> None:
    (check,) = await halt_and_verify([_Regenerating(on_after_stop=1)], timeout_s=1.0)
    assert check.halted and "stopped 1 more time(s)" in check.verified and "high voltage on" in check.verified, check
    (stuck,) = await halt_and_verify([_Regenerating(on_after_stop=10**6)], timeout_s=0.3)
    assert not stuck.halted and "high voltage on" in stuck.problem and "more stop(s) within 0.3 s" in stuck.problem, (
        stuck
    )
