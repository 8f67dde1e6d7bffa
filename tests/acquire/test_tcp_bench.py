"""A bench reached over its configured URIs (standalone twins on TCP/Modbus ports), as real hardware is."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Iterator
from pathlib import Path

import pytest

from acquire.config import BenchConfig
from acquire.errors import RefusedError
from acquire.rigs.bench import open_bench
from acquire.runner import ScanRequest, ScanRunner, build_plan
from devices.errors import NotReferencedError
from orbitct.scanfile import ScanFile
from tests.helpers.bench import SMALL_ERRORS
from tests.helpers.twin_bench import twin_bench

WORLD = "tcp-bench"
pytestmark = [pytest.mark.timeout(120), pytest.mark.system]


@pytest.fixture(scope="module")
def tcp_config() -> Iterator[BenchConfig]:
    with twin_bench(WORLD) as bench:
        yield bench.config


def _request(cfg: BenchConfig, out: Path) -> ScanRequest:
    return ScanRequest(
        config=cfg,
        out=out,
        orbit="sawtooth",
        frames=10,
        orbit_params={"amplitude_deg": 5.0},
        errors="custom",
        error_params=SMALL_ERRORS,
        seed=2,
        sim=False,
    )


def test_unreferenced_real_axes_are_not_referenced_by_a_scan(tcp_config: BenchConfig, tmp_path: Path) -> None:
    out = tmp_path / "refused.h5"

    async def main() -> None:
        async with open_bench(tcp_config, sim=False) as bench:
            with pytest.raises(RefusedError, match="not referenced; reference them first .*; nothing moved"):
                await ScanRunner(_request(tcp_config, out), rig=bench).run()  # by the pre-flight
            assert not await bench.hexapod.moving()
            # set-up without the pre-flight still never references real axes
            with pytest.raises(NotReferencedError, match="reference them first"):
                await bench.prepare(build_plan(_request(tcp_config, out), tcp_config))

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


def test_rehearsal_with_a_simulated_source_and_panel_warns(
    tcp_config: BenchConfig, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Real axes with a twin generator and panel: the motion runs, and the frames are said to be no scan's."""
    cfg = tcp_config.model_copy(
        update={"devices": tcp_config.devices.model_copy(update={"xray": "sim://bench", "detector": "sim://bench"})}
    )

    async def main() -> None:
        async with open_bench(cfg, sim=False) as bench:
            await asyncio.gather(bench.hexapod.reference(), bench.stage.reference())
            res = await ScanRunner(_request(cfg, tmp_path / "rehearsal.h5"), rig=bench).run()
            assert res.status == "complete", res.reason

    with caplog.at_level(logging.WARNING, logger="acquire.rigs.bench"):
        asyncio.run(main())
    assert "a rehearsal of the motion, not a scan to calibrate" in caplog.text
    with ScanFile(tmp_path / "rehearsal.h5") as sf:
        assert sf.frames.shape[1:] == (64, 64)  # the configuration's panel, not the twin's default
