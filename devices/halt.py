"""Emergency halt with proof: stop every device at once, then read each one back.

A stop that only sent its commands proves nothing: a reply may be lost or garbled, a device
may not have acted. :func:`halt_and_verify` sends every device its stop concurrently
(``#24`` to GCS controllers, X-rays off to the generator, ``STOP`` to a C-arm), then reads
each back: axes not moving, high voltage off and nothing exposing. A device counts as halted
only when its stop was acknowledged *and* its read-back confirms it; otherwise the check says
what could not be verified and why.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True)
class HaltCheck:
    """One device after an emergency halt: whether it is proven halted, what was read back, what went wrong."""

    device: str
    halted: bool
    verified: str = ""
    problem: str = ""

    def to_json(self) -> dict[str, Any]:
        """Plain values for a reply."""
        return asdict(self)


def can_halt(device: Any) -> bool:
    """Whether ``device`` has something to halt (axes or X-rays); a panel alone has not."""
    return hasattr(device, "xray_off") or hasattr(device, "stop")


def _text(exc: BaseException, name: str) -> str:
    if isinstance(exc, TimeoutError) and not str(exc):
        return "no reply in time"
    return (str(exc) or type(exc).__name__).removeprefix(f"{name}: ")


async def _send_stop(device: Any) -> None:
    if hasattr(device, "xray_off"):
        await device.xray_off()
    elif hasattr(device, "halt"):
        await device.halt()
    else:
        await device.stop()


async def read_back(device: Any) -> tuple[bool, str]:
    """(halted, what the device reports) from a fresh read-back."""
    if hasattr(device, "xray_off"):
        state = await device.read()
        if state["hv_on"] or state["exposing"]:
            return (
                False,
                f"generator reports high voltage {'on' if state['hv_on'] else 'off'}, "
                f"{'exposing' if state['exposing'] else 'not exposing'} (state {state['state']})",
            )
        return True, f"high voltage off, not exposing (state {state['state']})"
    if hasattr(device, "moving"):
        if await device.moving():
            return False, "axes still moving"
        return True, "axes not moving"
    state = await device.read()
    if state.get("moving"):
        return False, "still moving"
    return True, "not moving"


RECHECK_S = 0.05  # pause before stopping a device again that read back not halted


async def _halt_one(device: Any, timeout_s: float) -> HaltCheck:
    name = str(getattr(device, "name", device))
    problems: list[str] = []
    try:
        async with asyncio.timeout(timeout_s):
            await _send_stop(device)
    except Exception as exc:  # noqa: BLE001 - reported, never raised: the other devices still get their stop
        problems.append(f"stop not acknowledged ({_text(exc, name)})")
    halted, verified, first, again = False, "", "", 0
    try:
        async with asyncio.timeout(timeout_s):
            halted, verified = await read_back(device)
            # Something else may have commanded the device between the stop and the read-back (a scan that has not
            # yet seen the latch switching high voltage on for its next frame): stop it again until it stays halted.
            while not halted and not problems:
                first = first or verified
                await asyncio.sleep(RECHECK_S)
                await _send_stop(device)
                again += 1
                halted, verified = await read_back(device)
    except Exception as exc:  # noqa: BLE001
        if not (again and isinstance(exc, TimeoutError)):
            problems.append(f"read-back failed ({_text(exc, name)})")
        elif verified:  # it kept coming back: say what it read and how often it was stopped
            verified += f" (still, after {again} more stop(s) within {timeout_s:g} s)"
    if not halted and verified:
        problems.append(verified)
        verified = ""
    if halted and again:
        verified += f"; after the stop it read back {first!r}: stopped {again} more time(s)"
    return HaltCheck(name, halted and not problems, verified, "; ".join(problems))


async def halt_and_verify(devices: Iterable[Any], timeout_s: float = 1.0) -> list[HaltCheck]:
    """Stop every device that can be halted, all at once, and prove it by reading each back (never raises)."""
    targets = [d for d in devices if can_halt(d)]
    return list(await asyncio.gather(*(_halt_one(d, timeout_s) for d in targets)))


def summary(checks: Iterable[HaltCheck]) -> tuple[bool, str]:
    """(every device proven halted, one line saying so or naming what was not verified)."""
    checks = list(checks)
    if not checks:
        return False, "no device could be reached to halt"
    bad = [c for c in checks if not c.halted]
    if not bad:
        return True, "halted and verified: " + "; ".join(f"{c.device} {c.verified}" for c in checks)
    return False, "NOT verified: " + "; ".join(f"{c.device}: {c.problem}" for c in bad)
