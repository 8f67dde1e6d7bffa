"""The machines a scan runs on, behind one :class:`~acquire.engine.Rig` interface: the bench and the C-arm."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator

from acquire.config import BenchConfig, CArmConfig
from acquire.engine import Rig
from acquire.rigs.bench import BenchRig, open_bench
from acquire.rigs.carm import CArmRig, open_carm


@contextlib.asynccontextmanager
async def open_rig(config: BenchConfig | CArmConfig, *, sim: bool = False) -> AsyncIterator[Rig]:
    """Connect the rig a configuration names (its twins in-process when ``sim``); stopped and closed on exit."""
    opener = open_carm if isinstance(config, CArmConfig) else open_bench
    async with opener(config, sim=sim) as rig:  # type: ignore[arg-type]
        yield rig


__all__ = ["BenchRig", "CArmRig", "open_bench", "open_carm", "open_rig"]
