"""A panel twin of its own process follows a bench of twins elsewhere over their real protocols (GCS, Modbus)."""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Iterator

import numpy as np
import pytest

from devices.detector import Detector
from devices.hexapod import Hexapod
from devices.rotation_stage import RotationStage
from devices.twins.detector import DetectorTwin
from devices.twins.gcs import start_twin
from devices.twins.runtime import TwinThread
from devices.twins.world import SimWorld, get_world, reset_world
from devices.twins.xray import XrayTwin
from devices.xray import XrayGenerator

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def threads() -> Iterator[dict[str, TwinThread]]:
    """Hexapod, stage and generator twins in one world; a panel twin in a world of its own that follows them."""
    bench = reset_world("feed-bench")
    out = {
        "hexapod": start_twin("hexapod", world="feed-bench", time_scale=25.0),
        "rotation_stage": start_twin("rotation_stage", world="feed-bench", time_scale=25.0),
        "xray": TwinThread(XrayTwin(bench, time_scale=25.0)),
    }
    out["panel"] = TwinThread(
        DetectorTwin(reset_world("feed-panel"), rows=16, follow={k: t.uri for k, t in out.items()})
    )
    try:
        yield out
    finally:
        for name in ("panel", "xray", "rotation_stage", "hexapod"):  # the follower first
            out[name].stop()


@pytest.fixture
def bench_and_panel(threads: dict[str, TwinThread]) -> tuple[dict[str, str], SimWorld, str]:
    panel = threads["panel"]
    return {k: t.uri for k, t in threads.items() if k != "panel"}, panel.twin.world, panel.uri


def test_the_panel_images_the_followed_pose_on_the_followed_generators_exposure(
    bench_and_panel: tuple[dict[str, str], SimWorld, str],
) -> None:
    uris, panel_world, panel_uri = bench_and_panel

    async def main() -> None:
        async with (
            Hexapod("hexapod", uris["hexapod"]) as hexa,
            RotationStage("stage", uris["rotation_stage"]) as stage,
            XrayGenerator("xray", uris["xray"]) as gen,
            Detector("panel", panel_uri, timeout_s=10.0) as panel,
        ):
            await asyncio.gather(hexa.reference(), stage.reference())
            await asyncio.gather(hexa.move({"X": 2.0, "U": 3.0}), stage.move({"R": -90.0}))
            await panel.set_trigger("xray")
            await panel.arm()
            await gen.configure(kv=80.0, ma=1.0, exposure_ms=10.0)
            await gen.expose(release=True)
            frame = await panel.read_frame()  # taken on the generator's exposure, which only the feed saw
            assert frame.kind == "projection" and frame.shape == (16, 16)
            turn, pose = await stage.position(), await hexa.position()
            with panel_world.lock:  # the pose it imaged: the read-backs of the axes elsewhere (each with its noise)
                assert math.degrees(panel_world.stage_true_rad) == pytest.approx(turn["R"], abs=1e-3)
                np.testing.assert_allclose(panel_world.hexapod_true[:3], [pose[a] for a in "XYZ"], atol=1e-3)
                np.testing.assert_allclose(
                    np.degrees(panel_world.hexapod_true[3:]), [pose[a] for a in "UVW"], atol=1e-3
                )
                assert panel_world.xray_kv == 80.0 and panel_world.xray_frame_counter == 1

    asyncio.run(main())


def test_a_lost_generator_is_connected_again(threads: dict[str, TwinThread], caplog: pytest.LogCaptureFixture) -> None:
    """The generator restarts on its port: the panel logs the lost link, connects again, and takes the next
    exposure's frame; meanwhile it takes none."""
    port = threads["xray"].port
    with caplog.at_level(logging.WARNING, logger="devices.twins.feed"):
        threads["xray"].stop()
        # Wait for the loss to be noticed while the generator is gone: a fixed pause raced the feed under load
        # (a read that timed out rather than failed was retried once, by then against the restarted twin).
        deadline = time.monotonic() + 20.0
        while "lost the bench it images" not in caplog.text and time.monotonic() < deadline:
            time.sleep(0.05)
        assert "lost the bench it images" in caplog.text
        threads["xray"] = TwinThread(XrayTwin(get_world("feed-bench"), time_scale=25.0), port=port)
    twin = threads["xray"]
    deadline = time.monotonic() + 20.0  # the feed's monitor connects again (one retry, later under load)
    while twin.run_sync(lambda: twin.twin.connections) < 1 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert twin.run_sync(lambda: twin.twin.connections) >= 1

    async def main() -> None:
        async with (
            XrayGenerator("xray", threads["xray"].uri) as gen,
            Detector("panel", threads["panel"].uri, timeout_s=10.0) as panel,
        ):
            await panel.set_trigger("xray")
            await panel.arm()
            await gen.expose(release=True)
            assert (await panel.read_frame()).kind == "projection"

    asyncio.run(main())


def test_a_panel_following_a_bench_that_is_gone_stops_at_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """Stopped while it connects again (here without pause, so that the stop often lands inside a failing
    connect). Once in CI a stop that a failing connect swallowed (pymodbus connects with ``wait_for``, which on
    3.11 can lose a cancellation) left the feed retrying, and the twin's stop timed out after 5 s; the feed now
    honours a cancellation it finds pending. This test narrows the window; it cannot force the race."""
    import socket

    from devices.twins import feed

    monkeypatch.setattr(feed, "RETRY_S", 0.0)
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        gone = f"127.0.0.1:{s.getsockname()[1]}"
    for _ in range(5):
        panel = TwinThread(
            DetectorTwin(
                reset_world("feed-gone"),
                rows=8,
                follow={"hexapod": f"tcp://{gone}", "rotation_stage": f"tcp://{gone}", "xray": f"modbus://{gone}"},
            )
        )
        time.sleep(0.2)
        t = time.monotonic()
        panel.stop()
        assert time.monotonic() - t < 4.0
