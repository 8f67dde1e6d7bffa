"""A world fed from twins in other processes: what a standalone panel twin images, and when.

In one process the motion and generator twins write the true pose and every exposure into a shared
:class:`~devices.twins.world.SimWorld`. A panel twin in a process of its own cannot see that; :func:`follow_bench`
stands in for the trigger cable and the object on the table: it watches the generator over Modbus (a second,
read-only connection, as a monitor) and reads the hexapod and rotation stage over GCS when an exposure begins,
then writes their pose (read-backs: the hidden imperfections stay with the motion twins) and the exposure into
the panel's own world.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time

import numpy as np

from devices.hexapod import AXES as HEXAPOD_AXES
from devices.hexapod import Hexapod
from devices.rotation_stage import RotationStage
from devices.twins.world import SimWorld
from devices.xray import XrayGenerator

log = logging.getLogger(__name__)

#: how often the generator is asked whether it exposes (s)
POLL_S = 0.002
#: how often the pose is read while no exposure comes (s), so that darks and the console's view stay current
IDLE_POSE_S = 0.2
#: how long to wait before connecting again after a link is lost (s)
RETRY_S = 1.0


async def _read_pose(world: SimWorld, hexapod: Hexapod, stage: RotationStage) -> None:
    hexa, turn, pivot = await asyncio.gather(hexapod.position(), stage.position(), hexapod.pivot())
    pose = np.array([float(hexa[a]) for a in HEXAPOD_AXES])
    with world.lock:
        world.hexapod_true = np.concatenate([pose[:3], np.radians(pose[3:])])
        world.pivot_mm = (float(pivot["R"]), float(pivot["S"]), float(pivot["T"]))
        world.stage_true_rad = math.radians(float(next(iter(turn.values()))))


async def _follow_once(world: SimWorld, hexapod_uri: str, stage_uri: str, xray_uri: str, poll_s: float) -> None:
    async with (
        Hexapod("followed hexapod", hexapod_uri) as hexapod,
        RotationStage("followed rotation stage", stage_uri) as stage,
        XrayGenerator("followed generator", xray_uri, monitor=True) as generator,
    ):
        await _read_pose(world, hexapod, stage)
        last = int((await generator.read())["frame_counter"])
        posed_at, posed_this_exposure = time.monotonic(), False
        while True:
            state = await generator.read()
            counter = int(state["frame_counter"])
            if state["exposing"] and not posed_this_exposure:  # the object where it is while the exposure lasts
                await _read_pose(world, hexapod, stage)
                posed_at, posed_this_exposure = time.monotonic(), True
            if counter != last:
                if not posed_this_exposure:  # an exposure shorter than a poll: the pose right after it
                    await _read_pose(world, hexapod, stage)
                    posed_at = time.monotonic()
                with world.lock:
                    world.xray_kv, world.xray_ma = float(state["kv"]), float(state["ma"])
                    world.exposure_ms = float(state["exposure_ms"])
                    world.xray_frame_counter += max(counter - last, 1)  # the panel's trigger input
                last, posed_this_exposure = counter, False
            elif not state["exposing"] and time.monotonic() - posed_at > IDLE_POSE_S:
                await _read_pose(world, hexapod, stage)
                posed_at = time.monotonic()
            await asyncio.sleep(poll_s)


async def follow_bench(
    world: SimWorld, *, hexapod_uri: str, stage_uri: str, xray_uri: str, poll_s: float = POLL_S
) -> None:
    """Keep ``world`` fed from the hexapod, rotation stage and generator at these URIs until cancelled; a lost link
    is logged and connected again after :data:`RETRY_S` (meanwhile the panel sees no exposure: it takes no frame
    at a stale pose)."""
    while True:
        try:
            await _follow_once(world, hexapod_uri, stage_uri, xray_uri, poll_s)
        except Exception as exc:  # whatever broke the link: no trigger and no pose pass until it is back
            task = asyncio.current_task()
            if task is not None and task.cancelling():  # a stop that a failing connect swallowed (3.11): honour it
                raise asyncio.CancelledError from exc
            log.warning(
                "panel twin: lost the bench it images (%s: %s); connecting again in %g s",
                type(exc).__name__,
                exc,
                RETRY_S,
            )
            await asyncio.sleep(RETRY_S)
