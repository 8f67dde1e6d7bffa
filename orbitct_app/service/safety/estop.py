"""The emergency stop as the web server sees it: forward to the guard, fall back to the rig process, latch, tell.

The stop's fast path is the guard's own listener (``orbitct stop``, the web console's button).
``POST /stop`` on the main port forwards there too; when the guard is down it latches here and
asks the rig process to halt over its stop pipe; when neither can be reached the reply says so.
Every stop and reset is an event on the ``safety`` topic (``GET /stop/events``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

from orbitct_app.service.core.auth import Principal
from orbitct_app.service.core.events import EventBus
from orbitct_app.service.rig.client import RigClient
from orbitct_app.service.safety.client import GuardClient, GuardUnavailable
from orbitct_app.service.safety.latch import StopLatch

log = logging.getLogger("orbitct.service.stop")
TOPIC = "safety"
RIG_CONFIRM_TIMEOUT_S = 5.0


class EmergencyStop:
    """Stop, reset and the latch's state for the web server's routes."""

    def __init__(self, latch: StopLatch, guard: GuardClient, rig: RigClient, bus: EventBus) -> None:
        self.latch, self.guard, self.rig, self.bus = latch, guard, rig, bus

    def published(self, reply: dict[str, Any]) -> None:
        """A stop happened (told by the guard, or done here): one ``stop`` event."""
        self.bus.publish(TOPIC, "stop", {k: v for k, v in reply.items() if k != "accepted"})

    async def stop(self, who: Principal, reason: str, authorization: str | None) -> dict[str, Any]:
        """Stop through the guard, else through the rig process; the reply says what was verified and by which path."""
        scan_id = self.rig.busy
        reason = reason or f"emergency stop by {who.name}"
        try:
            reply = await self.guard.stop(authorization, reason, who)
            reply["via"] = "guard"
        except GuardUnavailable as exc:
            reply = await self._through_rig(who, reason, str(exc))
            with contextlib.suppress(Exception):  # the event is told after the halt; its failure never costs the reply
                log.error("emergency stop: %s; stopped through the rig process", exc)
                self.published(reply)
        reply["scan_aborted"] = scan_id
        return reply

    async def _through_rig(self, who: Principal, reason: str, guard_why: str) -> dict[str, Any]:
        """Latch in memory, halt over the rig process's links, then record the latch (the guard's order)."""
        by = f"{who.name} ({who.role})"
        self.latch.latch(by, reason, via="REST (guard unavailable)")
        base: dict[str, Any] = {
            "accepted": True,
            "latched": True,
            "by": by,
            "reason": reason,
            "via": "rig",
            "devices": [],
        }
        reply = await self._rig_halt(base, guard_why)
        reply["latch_recorded"] = await asyncio.to_thread(self.latch.record)
        if not reply["latch_recorded"]:
            reply["latch_problem"] = f"{self.latch.record_problem}; the stop holds in memory until it is recorded"
        return reply

    async def _rig_halt(self, base: dict[str, Any], guard_why: str) -> dict[str, Any]:
        _, future = self.rig.emergency_stop(base["reason"])
        if future is None:
            return {
                **base,
                "via": "none",
                "halted": False,
                "message": f"NOT verified: no process can reach the devices ({guard_why}; the rig process is "
                f"{self.rig.connection_state}); the stop is latched: stop the bench by hand",
            }
        try:
            answer = await asyncio.wait_for(asyncio.wrap_future(future), RIG_CONFIRM_TIMEOUT_S)
        except TimeoutError:
            return {
                **base,
                "halted": False,
                "message": f"NOT verified: halt sent to the rig process ({guard_why}), no confirmation within "
                f"{RIG_CONFIRM_TIMEOUT_S:g} s",
            }
        except Exception as exc:  # noqa: BLE001 - the stop is still latched; say what the rig answered
            return {
                **base,
                "halted": False,
                "message": f"NOT verified: halt sent to the rig process, which reported: {exc}",
            }
        return {
            **base,
            "halted": bool(answer["halted"]),
            "devices": answer["devices"],
            "message": f"{answer['message']} (through the rig process: {guard_why})",
        }

    def reset(self, who: Principal, note: str = "") -> dict[str, Any]:
        """Clear the latch (raises :class:`~orbitct_app.service.safety.latch.NotLatchedError` if clear); one event."""
        by = f"{who.name} ({who.role})"
        state = self.latch.reset(by, note)
        log.warning("emergency stop reset by %s%s", by, f": {note}" if note else "")
        self.bus.publish(TOPIC, "reset", {"by": by, "note": note, "utc": state["last_reset"]["utc"]})
        return self.state(state)

    def state(self, state: dict[str, Any] | None = None) -> dict[str, Any]:
        """The latch, and where the stop listener is."""
        return {
            **(state or self.latch.state()),
            "stop_url": f"{self.guard.url}/stop" if self.guard.url else None,
            "guard": self.guard.state,
        }

    def refusal(self, action: str) -> str | None:
        """Why ``action`` is refused now (None when no stop is latched)."""
        return self.latch.refusal(action)
