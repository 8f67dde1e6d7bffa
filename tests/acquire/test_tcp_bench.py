"""A bench reached over its configured URIs (standalone twins on TCP/Modbus ports), as real hardware is."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import pytest

from acquire.rigs.bench import open_bench
from acquire.config import BenchConfig
from acquire.runner import ScanRequest, ScanRunner
from devices.twins.detector import DetectorTwin
from devices.twins.gcs import start_twin
from devices.twins.runtime import TwinThread
from devices.twins.world import get_world
from devices.twins.xray import XrayTwin
from orbitct.scanfile import ScanFile
from tests.helpers.bench import SMALL_ERRORS, small_config

WORLD = "tcp-bench"
pytestmark = [pytest.mark.timeout(120), pytest.mark.system]


@pytest.fixture(scope="module")
def tcp_config() -> Iterator[BenchConfig]:
    world = get_world(WORLD)
    hexa = start_twin("hexapod", world=WORLD, time_scale=25.0)
    stage = start_twin("rotation_stage", world=WORLD, time_scale=25.0)
    xray = TwinThread(XrayTwin(world))
    det = TwinThread(DetectorTwin(world, rows=64, cols=64))
    uris = {"hexapod": hexa.uri, "rotation_stage": stage.uri, "xray": f"modbus://127.0.0.1:{xray.port}",
            "detector": f"tcp://127.0.0.1:{det.port}"}
    cfg = small_config()
    yield cfg.model_copy(update={"devices": cfg.devices.model_copy(update=uris)})
    for t in (det, xray):
        t.stop()
    for s in (hexa, stage):
        s.stop()


def _request(cfg: BenchConfig, out: Path) -> ScanRequest:
    return ScanRequest(config=cfg, out=out, orbit="sawtooth", frames=10, orbit_params={"amplitude_deg": 5.0},
                       errors="custom", error_params=SMALL_ERRORS, seed=2, sim=False)


def test_unreferenced_real_axes_are_not_referenced_by_a_scan(tcp_config: BenchConfig, tmp_path: Path) -> None:
    out = tmp_path / "refused.h5"

    async def main() -> None:
        async with open_bench(tcp_config, sim=False) as bench:
            res = await ScanRunner(_request(tcp_config, out), rig=bench).run()
            assert res.status == "aborted" and "not referenced" in res.reason and "reference them first" in res.reason
            assert not await bench.hexapod.moving()

    asyncio.run(main())
    assert not out.exists()  # nothing was recorded: the scan never started


def test_scan_over_configured_uris(tcp_config: BenchConfig, tmp_path: Path) -> None:
    out = tmp_path / "tcp.h5"

    async def main() -> None:
        async with open_bench(tcp_config, sim=False) as bench:
            await asyncio.gather(bench.hexapod.reference(), bench.stage.reference())  # the operator's step
            res = await ScanRunner(_request(tcp_config, out), rig=bench).run()
            assert res.status == "complete", res.reason

    asyncio.run(main())
    with ScanFile(out) as sf:
        assert sf.status == "complete" and sf.count_by_kind()["projection"] == 10
        assert not sf.has_geometry("truth")  # a real bench knows no truth
        assert set(sf.axes("encoders")) >= {"rotation_stage.R", "hexapod.U"}
