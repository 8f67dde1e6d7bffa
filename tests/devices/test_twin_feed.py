"""A panel twin of its own process follows a bench of twins elsewhere over their real protocols (GCS, Modbus)."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator

import numpy as np
import pytest

from devices.detector import Detector
from devices.hexapod import Hexapod
from devices.rotation_stage import RotationStage
from devices.twins.detector import DetectorTwin
from devices.twins.gcs import start_twin
from devices.twins.runtime import TwinThread
from devices.twins.world import SimWorld, reset_world
from devices.twins.xray import XrayTwin
from devices.xray import XrayGenerator

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def bench_and_panel() -> Iterator[tuple[dict[str, str], SimWorld, str]]:
    """Hexapod, stage and generator twins in one world; a panel twin in a world of its own that follows them."""
    bench = reset_world("feed-bench")
    threads = {"hexapod": start_twin("hexapod", world="feed-bench", time_scale=25.0),
               "rotation_stage": start_twin("rotation_stage", world="feed-bench", time_scale=25.0),
               "xray": TwinThread(XrayTwin(bench, time_scale=25.0))}
    uris = {k: t.uri for k, t in threads.items()}
    panel_world = reset_world("feed-panel")
    panel = TwinThread(DetectorTwin(panel_world, rows=16, follow=uris))
    try:
        yield uris, panel_world, panel.uri
    finally:
        for t in (panel, *threads.values()):
            t.stop()


def test_the_panel_images_the_followed_pose_on_the_followed_generators_exposure(
        bench_and_panel: tuple[dict[str, str], SimWorld, str]) -> None:
    uris, panel_world, panel_uri = bench_and_panel

    async def main() -> None:
        async with Hexapod("hexapod", uris["hexapod"]) as hexa, RotationStage("stage", uris["rotation_stage"]) as stage, \
                XrayGenerator("xray", uris["xray"]) as gen, Detector("panel", panel_uri, timeout_s=10.0) as panel:
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
                np.testing.assert_allclose(np.degrees(panel_world.hexapod_true[3:]), [pose[a] for a in "UVW"], atol=1e-3)
                assert panel_world.xray_kv == 80.0 and panel_world.xray_frame_counter == 1

    asyncio.run(main())
