"""A simulated bench in one process: rotation stage, X-ray generator and panel share one world.

The generator's exposure triggers the panel, and the panel images the object at the stage's
TRUE angle (which differs from the encoder read-back on an imperfect twin).
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from devices.factory import open_device, opened
from devices.twins.world import reset_world
from orbitct.geometry import ViewGeometry

pytestmark = [pytest.mark.timeout(120), pytest.mark.system]


def test_exposure_frames_follow_the_true_stage_angle() -> None:
    world = reset_world("detbench")

    async def main() -> None:
        stage = await open_device("rotation_stage", "stage", "sim://detbench", time_scale=100)
        try:
            async with (
                opened("detector", "det", "sim://detbench", rows=32, trigger="xray") as det,
                opened("xray", "xray", "sim://detbench", prep_s=0.01, heartbeat_s=0) as gen,
            ):
                await stage.reference()
                await det.arm()
                truths = []
                for angle in (10.0, 40.0):
                    await stage.move({"R": angle})
                    await gen.expose()
                    frame = await det.read_frame(timeout_s=10.0)
                    R, t = world.object_pose()
                    lab = ViewGeometry.from_carm(0.0, 0.0, 785.0, 1200.0, det.geometry)
                    expected = ViewGeometry.from_object_poses(lab, R, t).vectors[0]
                    np.testing.assert_allclose(frame.meta["truth_vectors"], expected, atol=1e-9)
                    truths.append(np.asarray(frame.meta["truth_vectors"]))
                # the source, seen from the object, turned by about the commanded 30 degrees
                s0, s1 = truths[0][:3], truths[1][:3]
                turned = np.degrees(np.arccos(np.dot(s0, s1) / np.linalg.norm(s0) / np.linalg.norm(s1)))
                assert turned == pytest.approx(30.0, abs=1.0)
        finally:
            await stage.close()

    asyncio.run(main())
