"""The bluesky adapter's fixtures: a RunEngine, and a bench's ophyd-async devices connected to its twins."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest
from bluesky import RunEngine
from bluesky.run_engine import call_in_bluesky_event_loop

from acquire.config import BenchConfig
from orbitct_bluesky import Bench


@pytest.fixture
def RE() -> RunEngine:
    """A RunEngine (its event loop, where the devices connect, runs from here on)."""
    return RunEngine({})


@pytest.fixture
def open_bench(RE: RunEngine) -> Iterator[Callable[[BenchConfig], Bench]]:
    """Connect a bench's ophyd-async devices to its twins (``sim://``); disconnected (twins stopped) afterwards."""
    opened: list[Bench] = []

    def make(config: BenchConfig) -> Bench:
        bench = Bench.from_config(config, sim=True)
        opened.append(bench)

        async def connect() -> None:
            for device in bench.devices:
                await device.connect(timeout=30.0)

        call_in_bluesky_event_loop(connect())
        return bench

    yield make

    async def close(bench: Bench) -> None:
        for device in bench.devices:
            await device.disconnect()

    for bench in opened:
        call_in_bluesky_event_loop(close(bench))
