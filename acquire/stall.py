"""Progress bounds: a device call that makes no progress in time ends the scan, naming the device.

These bounds sit above the drivers' per-command time-outs: a panel that answers every poll but
delivers a frame only every 25 s, or an arm that never arrives, is a stall even though each
exchange is in time. The call is cancelled (drivers clean up: X-rays off, late replies dropped)
and :class:`~acquire.errors.StallError` names the device and the bound.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable
from typing import TypeVar

from acquire.errors import StallError

T = TypeVar("T")


async def within(bound_s: float, device: str, what: str, setting: str, call: Awaitable[T]) -> T:
    """Await ``call``; past ``bound_s`` cancel it and raise :class:`StallError` ("``device`` ``what`` within ...")."""
    limit = asyncio.timeout(bound_s)
    try:
        async with limit:
            return await call
    except TimeoutError:
        if limit.expired():
            raise StallError(device, what, bound_s, setting) from None
        raise
