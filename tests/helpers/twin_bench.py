"""A bench of standalone twins on TCP/Modbus ports, reached over its configured URIs as real hardware is."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

from acquire.config import BenchConfig
from devices.factory import opened
from devices.twins.detector import DetectorTwin
from devices.twins.gcs import start_twin
from devices.twins.runtime import TwinThread
from devices.twins.world import reset_world
from devices.twins.xray import XrayTwin
from tests.helpers.bench import small_config


@dataclass
class TwinBench:
    """The four twins (their threads) and a bench configuration that names their endpoints."""

    config: BenchConfig
    hexapod: TwinThread
    stage: TwinThread
    xray: TwinThread
    detector: TwinThread

    def reference(self) -> None:
        """The operator's step before a scan on real axes: servo on and reference both controllers."""

        async def main() -> None:
            async with (
                opened("hexapod", "hexapod", self.hexapod.uri) as hexa,
                opened("rotation_stage", "stage", self.stage.uri) as stage,
            ):
                await asyncio.gather(hexa.reference(), stage.reference())

        asyncio.run(main())


@contextlib.contextmanager
def twin_bench(world: str, *, time_scale: float = 25.0, size: int = 64) -> Iterator[TwinBench]:
    """Start the twins of one world in this process; stop them on exit."""
    w = reset_world(world)
    hexa = start_twin("hexapod", world=world, time_scale=time_scale)
    stage = start_twin("rotation_stage", world=world, time_scale=time_scale)
    xray = TwinThread(XrayTwin(w, time_scale=time_scale))
    det = TwinThread(DetectorTwin(w, rows=size, cols=size))
    uris = {"hexapod": hexa.uri, "rotation_stage": stage.uri, "xray": xray.uri, "detector": det.uri}
    cfg = small_config(size)
    try:
        yield TwinBench(cfg.model_copy(update={"devices": cfg.devices.model_copy(update=uris)}), hexa, stage, xray, det)
    finally:
        for t in (det, xray, hexa, stage):
            t.stop()
