"""Read the simulated bench's twins back over connections of the test's own (not through the service)."""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from typing import Any

from devices.factory import open_device
from devices.halt import read_back

OPTIONS: dict[str, dict[str, Any]] = {
    "hexapod": {"timeout_s": 2.0},
    "rotation_stage": {"timeout_s": 2.0},
    "xray": {"timeout_s": 2.0, "monitor": 1},
}


def twins_halted(links: Mapping[str, Any]) -> dict[str, tuple[bool, str]]:
    """``{device: (halted, what it reads)}`` for every axis controller and the generator: axes not moving, high voltage
    off and not exposing, as the twins themselves answer a fresh connection."""

    async def read() -> dict[str, tuple[bool, str]]:
        out = {}
        for kind, options in OPTIONS.items():
            if kind not in links:
                continue
            device = await open_device(kind, kind, links[kind].uri, **options)
            try:
                out[kind] = await read_back(device)
            finally:
                await device.close()
        return out

    return asyncio.run(read())
