"""X-ray generator driver against its Modbus twin over a loopback socket: exposures, refusals, faults."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import Awaitable, Callable, Iterator
from typing import Any

import pytest

from devices.errors import (
    ControllerError,
    DeviceError,
    DeviceTimeoutError,
    FaultActiveError,
    InterlockOpenError,
    NotConnectedError,
    OutOfLimitsError,
    ProtocolError,
    UriError,
)
from devices.factory import open_device, opened
from devices.sim import twin_of
from devices.twins.runtime import TwinThread
from devices.twins.world import SimWorld
from devices.twins.xray import XrayTwin
from devices.xray import XrayGenerator
from devices.xray_registers import FaultCode

pytestmark = [pytest.mark.timeout(60), pytest.mark.system]


@pytest.fixture()
def twin() -> Iterator[tuple[XrayTwin, TwinThread]]:
    tw = XrayTwin(SimWorld(), prep_s=0.03)
    th = TwinThread(tw)
    yield tw, th
    th.stop()


def run(twin: tuple[XrayTwin, TwinThread], body: Callable[[XrayGenerator], Awaitable[Any]], **options: Any) -> Any:
    """Connect a real driver to the twin, run ``body``, close."""
    options.setdefault("heartbeat_s", 0)
    options.setdefault("timeout_s", 0.5)

    async def main() -> Any:
        gen = XrayGenerator("xray", f"modbus://127.0.0.1:{twin[1].port}", **options)
        await gen.connect()
        try:
            return await body(gen)
        finally:
            await gen.close()

    return asyncio.run(main())


def test_describe_configure_and_expose(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        info = await gen.describe()
        assert info.model == "SimGen XR-150" and info.serial == "XG-0001" and info.firmware == "1.02"
        await gen.configure(kv=80.0, ma=2.5, exposure_ms=20)
        state = await gen.read()
        assert (state["kv"], state["ma"], state["exposure_ms"], state["state"]) == (80.0, 2.5, 20, "IDLE")
        reports: list[str] = []
        prep = gen.prepare()
        prep.watch(lambda p: reports.append(p.message))
        await prep
        assert (await gen.read())["ready"] and "READY" in reports
        assert await gen.expose() == 1
        assert await gen.trigger() == 2  # stays prepared: READY again after DONE
        state = await gen.read()
        assert state["frame_counter"] == 2 and state["state"] == "READY" and state["last_exposure_ms"] >= 19
        await gen.xray_off()
        assert (await gen.read())["state"] == "IDLE"

    run(twin, body)
    assert tw.world.xray_frame_counter == 2 and tw.world.xray_kv == 80.0 and not tw.world.exposing


def test_expose_from_idle_prepares_first(twin: tuple[XrayTwin, TwinThread]) -> None:
    async def body(gen: XrayGenerator) -> int:
        return await gen.expose()

    assert run(twin, body) == 1


def test_out_of_range_settings_refused_by_driver_and_twin(twin: tuple[XrayTwin, TwinThread]) -> None:
    async def body(gen: XrayGenerator) -> None:
        with pytest.raises(OutOfLimitsError, match="kv=200"):
            await gen.configure(kv=200, ma=1, exposure_ms=10)
        assert gen._client is not None
        reply = await gen._client.write_register(0, 2000, device_id=1)  # bypass the driver check
        assert reply.isError() and reply.exception_code == 3
        assert (await gen.read())["kv"] == 90.0

    run(twin, body)


def test_open_interlock_refuses_and_exposes_nothing(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, th = twin
    th.call(tw.set_door, False)

    async def body(gen: XrayGenerator) -> None:
        with pytest.raises(InterlockOpenError, match="door"):
            await gen.expose()
        with pytest.raises(InterlockOpenError):
            await gen.prepare()
        # the twin refuses on its own too, whatever a client writes
        assert gen._client is not None
        await gen._client.write_coil(0, True, device_id=1)
        await gen._client.write_coil(1, True, device_id=1)
        await asyncio.sleep(0.1)
        state = await gen.read()
        assert state["frame_counter"] == 0 and state["state"] == "IDLE" and state["refusal"] == "INTERLOCK_OPEN"

    run(twin, body)
    assert tw.world.xray_frame_counter == 0


def test_software_interlock_refuses_high_voltage_until_it_clears(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin
    latched: list[str] = ["emergency stop by test: smoke"]

    async def body(gen: XrayGenerator) -> None:
        gen.interlock = lambda: latched[0] if latched else None
        with pytest.raises(InterlockOpenError, match="high voltage refused: emergency stop by test: smoke"):
            await gen.prepare()
        with pytest.raises(InterlockOpenError, match="high voltage refused"):
            await gen.expose()
        state = await gen.read()
        assert state["hv_on"] is False and state["frame_counter"] == 0
        latched.clear()  # reset: exposures work again
        await gen.expose(release=True)
        assert (await gen.read())["frame_counter"] == 1

    run(twin, body)
    assert tw.world.xray_frame_counter == 1


def test_door_opening_during_exposure_aborts(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, th = twin

    async def body(gen: XrayGenerator) -> None:
        await gen.configure(90, 1, 400)
        await gen.prepare()
        status = gen.expose()
        await asyncio.sleep(0.1)
        th.call(tw.set_door, False)
        with pytest.raises(InterlockOpenError, match="during exposure"):
            await status
        state = await gen.read()
        assert state["frame_counter"] == 0 and state["fault"] == "INTERLOCK_OPENED"
        with pytest.raises(FaultActiveError):
            await gen.reset_fault()  # door still open
        th.call(tw.set_door, True)
        await asyncio.sleep(0.05)
        await gen.reset_fault()
        assert await gen.expose() == 1

    run(twin, body)


def test_active_fault_refuses(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, th = twin
    th.call(tw.raise_fault, FaultCode.GENERATOR)

    async def body(gen: XrayGenerator) -> None:
        with pytest.raises(FaultActiveError, match="GENERATOR"):
            await gen.expose()
        assert (await gen.read())["frame_counter"] == 0
        await gen.xray_off()  # always allowed
        await gen.reset_fault()
        assert await gen.expose() == 1

    run(twin, body)


def test_device_error_is_named(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        tw.faults.error_next = 1
        with pytest.raises(ControllerError) as err:
            await gen.read()
        assert err.value.code == 4 and "DEVICE_FAILURE" in str(err.value)
        assert (await gen.read())["state"] == "IDLE"

    run(twin, body)


def test_latency_times_out_then_recovers(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        tw.faults.latency_s = 1.0
        with pytest.raises(DeviceTimeoutError, match="no reply"):
            await gen.read()
        tw.faults.latency_s = 0.0
        await asyncio.sleep(1.2)
        assert (await gen.read())["state"] == "IDLE"

    run(twin, body, timeout_s=0.2)


def test_garbled_reply_is_a_protocol_error(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        tw.faults.garble_next = 1
        with pytest.raises(ProtocolError, match="garbled"):
            await gen._request_once("read", lambda c: c.read_input_registers(0, count=4, device_id=1))
        # the normal path reconnects and reads fine
        assert (await gen.read())["state"] == "IDLE"

    run(twin, body, timeout_s=0.2)


def test_garbled_heartbeat_reply_resyncs_before_the_watchdog_fires(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        await gen.prepare()
        tw.faults.garble_next = 1  # the next reply is a heartbeat's
        await asyncio.sleep(1.0)  # twice the watchdog
        assert gen._link_fault is not None and "garbled" in gen._link_fault[2]
        state = await gen.read()
        assert state["state"] == "READY" and state["fault"] == "NONE"  # the link came back in time
        assert await gen.expose() == 1

    run(twin, body, heartbeat_s=0.05, watchdog_ms=500)


def test_watchdog_fault_names_the_link_fault_that_starved_it(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        await gen.prepare()
        tw.faults.latency_s = 0.6  # heartbeats time out, the generator's watchdog fires
        await asyncio.sleep(1.5)
        tw.faults.latency_s = 0.0
        await asyncio.sleep(0.7)
        with pytest.raises(FaultActiveError, match=r"WATCHDOG.*link fault at .*no reply"):
            await gen.expose()
        await gen.reset_fault()
        assert await gen.expose() == 1

    run(twin, body, heartbeat_s=0.05, watchdog_ms=300, timeout_s=0.2)


def test_dropped_connection_reconnects_for_reads(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        tw.faults.drop_next = 1
        assert (await gen.read())["state"] == "IDLE"  # one reconnect, read repeated
        tw.faults.drop_next = 1
        with pytest.raises(NotConnectedError):
            await gen._request_once("read", lambda c: c.read_input_registers(0, count=4, device_id=1))

    run(twin, body, timeout_s=0.3)


def test_exposure_is_never_retried_after_a_lost_reply(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        await gen.prepare()
        tw.request_log.clear()
        tw.faults.match = "fc5:1=[1]"  # the expose request (coil 1 set) itself
        tw.faults.drop_next = 1
        with pytest.raises(NotConnectedError, match="NOT retried"):
            await gen.expose()
        assert list(tw.request_log).count("fc5:1=[1]") == 1  # the expose request went out exactly once
        state = await gen.read()
        assert state["state"] == "IDLE" and not state["hv_on"]
        assert state["frame_counter"] <= 1

    run(twin, body, timeout_s=0.3)
    assert tw.world.xray_frame_counter <= 1


def test_missing_frame_is_reported_not_retried(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        tw.faults.missing_frame_next = 1
        with pytest.raises(DeviceError, match="missing frame"):
            await gen.expose()
        assert (await gen.read())["frame_counter"] == 0
        assert await gen.expose() == 1

    run(twin, body)


def test_heartbeat_feeds_watchdog_and_notices_silent_generator(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, th = twin

    async def body(gen: XrayGenerator) -> None:
        await gen.prepare()
        await asyncio.sleep(0.5)  # longer than the watchdog: the heartbeat keeps it fed
        assert (await gen.read())["state"] == "READY"
        tw.heartbeat_frozen = True
        await asyncio.sleep(0.8)
        with pytest.raises(DeviceTimeoutError, match="heartbeat stopped"):
            await gen.expose()

    run(twin, body, heartbeat_s=0.05, watchdog_ms=300)


def test_generator_watchdog_faults_without_heartbeat(twin: tuple[XrayTwin, TwinThread]) -> None:
    async def body(gen: XrayGenerator) -> None:
        await gen.prepare()
        await asyncio.sleep(0.5)
        state = await gen.read()
        assert state["state"] == "FAULT" and state["fault"] == "WATCHDOG" and not state["hv_on"]

    run(twin, body, heartbeat_s=0, watchdog_ms=200)


def test_sim_uri_starts_in_process_twin() -> None:
    async def main() -> None:
        async with opened("xray", "xray", "sim://xraytest?prep_s=0.01") as gen:
            assert twin_of(gen) is not None
            assert await gen.expose() == 1
            assert twin_of(gen).world.name == "xraytest"

    asyncio.run(main())


def test_bad_uri_and_options() -> None:
    async def main() -> None:
        with pytest.raises(UriError, match="allowed"):
            await open_device("xray", "xray", "sim://bench", bogus=1)

    asyncio.run(main())
    with pytest.raises(UriError, match="scheme"):
        XrayGenerator("xray", "http://x")
    with pytest.raises(UriError, match="modbus://"):  # the driver never sees sim://: devices.sim resolves it
        XrayGenerator("xray", "sim://bench")


def test_unreachable_generator() -> None:
    async def main() -> None:
        gen = XrayGenerator("xray", "modbus://127.0.0.1:1", timeout_s=0.3, heartbeat_s=0)
        with pytest.raises(NotConnectedError, match="cannot connect"):
            await gen.connect()

    asyncio.run(main())


def test_unreleased_exposure_is_released_before_the_next(twin: tuple[XrayTwin, TwinThread]) -> None:
    async def body(gen: XrayGenerator) -> None:
        assert await gen.expose() == 1
        assert gen._client is not None
        await gen._client.write_coil(1, True, device_id=1)  # a client that exposes and never releases
        await asyncio.sleep(0.1)
        assert (await gen.read())["state"] == "DONE"
        assert await gen.expose() == 3
        await gen._client.write_coil(1, True, device_id=1)  # exposure 4 ...
        await asyncio.sleep(0.1)
        await gen._client.write_coil(0, False, device_id=1)  # ... prep dropped, expose request left high
        assert await gen.expose() == 5

    run(twin, body)


def test_cancelled_exposure_switches_xrays_off(twin: tuple[XrayTwin, TwinThread]) -> None:
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        await gen.configure(90, 1, 2000)
        status = gen.expose()
        for _ in range(200):
            if tw.world.exposing:
                break
            await asyncio.sleep(0.01)
        assert tw.world.exposing
        status.cancel()  # an abort
        with pytest.raises(asyncio.CancelledError):
            await status
        state = await gen.read()
        assert state["state"] == "IDLE" and not state["hv_on"] and state["frame_counter"] == 0
        assert not tw.world.exposing

    run(twin, body)


def test_high_voltage_goes_off_when_nothing_exposes(twin: tuple[XrayTwin, TwinThread]) -> None:
    """After an exposure (or a prepare) high voltage stays on only ``hold_s``; an exposure inside it needs no new
    preparation, one after it prepares again."""
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        assert await gen.expose() == 1
        assert tw.state.name == "READY"  # held for the next exposure
        await asyncio.sleep(0.05)
        assert await gen.expose() == 2  # within the hold: no preparation in between
        prepared = tw.dose_seconds()[0]
        await asyncio.sleep(0.4)
        assert tw.state.name == "IDLE" and not tw.prep_req  # nothing exposed for longer than the hold: HV off
        assert tw.dose_seconds()[0] == pytest.approx(prepared, abs=0.2)
        await gen.prepare()
        await asyncio.sleep(0.4)
        assert tw.state.name == "IDLE"  # a preparation with no exposure after it ends the same way
        assert await gen.expose() == 3  # prepares again
        hv, exposing = tw.dose_seconds()
        assert 0 < exposing < hv
        assert await gen.expose(release=True) == 4  # the next exposure is far away: off at once, no hold
        await asyncio.sleep(0.05)
        assert tw.state.name == "IDLE"

    run(twin, body, hold_s=0.15)


def test_an_exposure_right_after_the_hold_fired_waits_for_its_request_not_its_time_out(
    twin: tuple[XrayTwin, TwinThread],
) -> None:
    """The hold's X-rays-off request, once on the wire, runs to its reply: cutting it short used to leave the next
    exposure waiting for a reply that never came (found under load by the exposure's stall bound)."""
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        assert await gen.expose() == 1
        tw.faults.latency_s = 0.3  # the hold (0.05 s) fires and its request waits 0.3 s for the reply
        await asyncio.sleep(0.1)
        assert gen._hold_sending
        tw.faults.latency_s = 0.0
        t0 = asyncio.get_running_loop().time()
        assert await asyncio.wait_for(gen.expose(), 3.0) == 2
        assert asyncio.get_running_loop().time() - t0 < 1.5
        await asyncio.wait_for(gen.xray_off(), 1.0)

    run(twin, body, hold_s=0.05, timeout_s=2.0)


def test_a_late_reply_to_a_read_cut_short_is_skipped_and_nothing_is_printed(
    twin: tuple[XrayTwin, TwinThread], caplog: pytest.LogCaptureFixture
) -> None:
    """A read cut short, and the next one sent while the generator still works on it: its late reply is skipped by
    its transaction id and the next read gets its own. pymodbus's ERROR line for the skip, with a dump of the last
    frames, reached the terminal in the middle of ``make demo``; the driver names every failure itself."""
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        tw.faults.latency_s = 0.3
        cut_short = asyncio.ensure_future(gen.read())
        await asyncio.sleep(0.1)
        cut_short.cancel()
        with pytest.raises(asyncio.CancelledError):
            await cut_short
        assert (await gen.read())["state"] == "IDLE"

    run(twin, body, timeout_s=1.0)
    assert not [r.getMessage() for r in caplog.records if r.name.startswith("pymodbus")]


def test_the_twin_answers_overlapping_requests_in_order_under_their_own_ids(twin: tuple[XrayTwin, TwinThread]) -> None:
    """Two requests on one connection, the second sent while the first waits (the latency fault): two replies, in
    order, each under its own transaction id (pymodbus's own server answered the first under the second's id)."""
    tw, th = twin
    tw.faults.latency_s = 0.2
    read_inputs = bytes([0, 1, 0, 0, 0, 6, 1, 4, 0, 0, 0, 2])  # transaction 1: two input registers
    read_bits = bytes([0, 2, 0, 0, 0, 6, 1, 2, 0, 0, 0, 5])  # transaction 2: five discrete inputs
    with socket.create_connection(("127.0.0.1", th.port), timeout=3.0) as conn:
        conn.sendall(read_inputs)
        time.sleep(0.05)
        conn.sendall(read_bits)
        replies = b""
        while len(replies) < 13 + 10:  # 9 + 2 * 2 bytes, then 9 + 1
            replies += conn.recv(64)
    first, second = replies[:13], replies[13:]
    assert (first[1], first[7], first[8]) == (1, 4, 4) and (second[1], second[7], second[8]) == (2, 2, 1)


def test_a_reply_to_another_request_is_refused(twin: tuple[XrayTwin, TwinThread]) -> None:
    """A well-formed reply under the request's transaction id that answers another function (a faulty gateway; the
    twin's ``misanswer`` fault): refused, the link starts afresh and the read is repeated once; twice is an error."""
    tw, _ = twin

    async def body(gen: XrayGenerator) -> None:
        tw.faults.misanswer_next = 1
        assert (await gen.read())["state"] == "IDLE"
        tw.faults.misanswer_next = 2
        with pytest.raises(ProtocolError, match="another request"):
            await gen.read()
        assert (await gen.read())["state"] == "IDLE"

    run(twin, body)
