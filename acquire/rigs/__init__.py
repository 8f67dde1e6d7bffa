"""The machines a scan runs on, behind one :class:`~acquire.rig.Rig` interface: the bench and the C-arm."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from acquire.config import BenchConfig, CArmConfig
from acquire.rig import Rig
from acquire.rigs.bench import BenchRig, open_bench
from acquire.rigs.carm import CArmRig, open_carm
from acquire.rigs.kinds import RigKind, rig_kind
from acquire.rigs.links import DeviceLink


def rig_links(config: BenchConfig | CArmConfig, *, sim: bool) -> dict[str, DeviceLink]:
    """Where each device of the rig is reached (``sim``: ``sim://`` URIs carrying twin and driver options)."""
    return rig_kind(config).links(config, sim=sim)


@contextlib.asynccontextmanager
async def open_rig(
    config: BenchConfig | CArmConfig, *, sim: bool = False, links: Mapping[str, DeviceLink] | None = None
) -> AsyncIterator[Rig]:
    """Connect the rig a configuration names (its twins in-process when ``sim``, or at ``links``); closed on exit."""
    async with rig_kind(config).open(config, sim=sim, links=links) as rig:
        yield rig


@dataclass
class RunningTwins:
    """The twins of a rig running in this process: the links drivers elsewhere use, and the twins themselves."""

    links: dict[str, DeviceLink] = field(default_factory=dict)
    twins: dict[str, Any] = field(default_factory=dict)


@contextlib.contextmanager
def sim_twins(config: BenchConfig | CArmConfig, ports: Mapping[str, int] | None = None) -> Iterator[RunningTwins]:
    """Run the twins of a rig in this process (on ``ports`` where given, else free ports) until the block ends.

    The links are what a driver in another process uses to reach them: loopback endpoints and the
    driver's own options (the twins' options stay here).
    """
    from devices.sim import start_twin

    running = RunningTwins()
    try:
        for kind, link in rig_links(config, sim=True).items():
            options = {**link.options, "port": int((ports or {}).get(kind, 0))}
            twin, driver_options = start_twin(kind, link.uri, options)
            running.twins[kind] = twin
            running.links[kind] = DeviceLink(twin.endpoint, driver_options)
        yield running
    finally:
        for twin in reversed(list(running.twins.values())):
            twin.stop()


__all__ = [
    "BenchRig",
    "CArmRig",
    "DeviceLink",
    "RigKind",
    "RunningTwins",
    "open_bench",
    "open_carm",
    "open_rig",
    "rig_kind",
    "rig_links",
    "sim_twins",
]
