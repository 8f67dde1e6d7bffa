"""The web server's handle on the guard process: start it, restart it if it dies, forward stops to it."""

from __future__ import annotations

import logging
import multiprocessing as mp
import secrets
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import httpx

from acquire.rigs.links import DeviceLink
from orbitct_app.service.core.auth import ON_BEHALF_HEADER, Principal
from orbitct_app.service.core.children import Backoff, end_child
from orbitct_app.service.core.settings import ServiceSettings

log = logging.getLogger("orbitct.service.guard")
_CTX = mp.get_context("spawn")
START_TIMEOUT_S = 30.0
FORWARD_TIMEOUT_S = 10.0


class GuardUnavailable(Exception):
    """The guard process cannot take a stop now; the message says why."""


class GuardClient:
    """Starts the guard process (its own stop listener), keeps it running, and forwards stops to it."""

    def __init__(
        self, settings: ServiceSettings, flag: Any, dev_token: str | None, on_stop: Callable[[dict[str, Any]], None]
    ) -> None:
        self.settings, self.flag, self.dev_token, self._on_stop = settings, flag, dev_token, on_stop
        self._forward_secret = secrets.token_urlsafe(32)  # stops of signed-in console users (no token of theirs here)
        self.state = "not started"
        self.port: int | None = None
        self._links: dict[str, tuple[str, dict[str, Any]]] = {}
        self._process: Any = None
        self._conn: Any = None
        self._ready = threading.Event()
        self._closing = False
        self._backoff = Backoff()
        self._started_at = 0.0

    @property
    def host(self) -> str:
        """Where the stop listener listens (the service's host)."""
        return self.settings.host

    @property
    def url(self) -> str | None:
        """Base URL of the stop listener once it listens."""
        if self.port is None:
            return None
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.port}"

    @property
    def alive(self) -> bool:
        """Whether the guard listens now."""
        return self.state == "listening" and self._process is not None and self._process.is_alive()

    def start(self, links: Mapping[str, DeviceLink]) -> None:
        """Start the guard for these device links and wait until it listens."""
        self._links = {k: (v.uri, dict(v.options)) for k, v in links.items()}
        port = self.settings.stop_port
        self.port = None
        self._spawn(self.settings.port + 1 if port is None else port)

    def _spawn(self, port: int) -> None:
        from orbitct_app.service.safety.guard import guard_main

        parent, child = _CTX.Pipe()
        self._ready.clear()
        self.state = "starting"
        s = self.settings
        self._process = _CTX.Process(
            target=guard_main,
            name="orbitct-guard",
            daemon=True,
            args=(
                self._links,
                str(s.data_dir),
                self.flag,
                s.host,
                port,
                [t.model_dump() for t in s.tokens],
                str(s.tokens_path),
                self.dev_token,
                child,
                s.bench_nice - 1 if s.bench_nice < 0 else 0,
                self._forward_secret,
            ),
        )
        self._process.start()
        child.close()
        self._conn = parent
        self._started_at = time.monotonic()
        threading.Thread(target=self._read, args=(parent, port), name="orbitct-guard-events", daemon=True).start()
        if not self._ready.wait(START_TIMEOUT_S):
            self.state = f"failed: the guard did not start within {START_TIMEOUT_S:g} s"
        if self.state != "listening":
            log.error("guard: %s", self.state)

    def _read(self, conn: Any, port: int) -> None:
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                break
            kind = message[0]
            if kind == "ready":
                self.port, self.state = int(message[1]), "listening"
                self._ready.set()
            elif kind == "failed":
                self.state = f"failed: {message[1]}"
                self._ready.set()
            elif kind == "stopped":
                try:
                    self._on_stop(message[1])
                except Exception:  # the reader must survive anything
                    log.exception("publishing a stop")
        self._ready.set()
        if self._closing:
            return
        uptime = time.monotonic() - self._started_at
        delay = self._backoff.delay(uptime)
        self.state = f"restarting: the guard process ended (restart {self._backoff.restarts} in {delay:g} s)"
        log.error("guard: %s", self.state)
        time.sleep(delay)
        if not self._closing:
            self._spawn(self.port if self.port is not None else port)  # the same port: clients keep their URL

    async def stop(self, authorization: str | None, reason: str, who: Principal) -> dict[str, Any]:
        """Forward a stop to the guard with the caller's own token, or (a console session, no token here) with this
        service's forwarding secret on behalf of ``who``; the guard's verified reply."""
        if not self.alive or self.url is None:
            raise GuardUnavailable(f"the guard is not listening ({self.state})")
        headers = (
            {"Authorization": authorization}
            if authorization
            else {"Authorization": f"Bearer {self._forward_secret}", ON_BEHALF_HEADER: f"{who.name}|{who.role}"}
        )
        try:
            async with httpx.AsyncClient(timeout=FORWARD_TIMEOUT_S) as client:
                r = await client.post(f"{self.url}/stop", json={"reason": reason}, headers=headers)
        except httpx.HTTPError as exc:
            raise GuardUnavailable(f"the guard did not answer ({exc or 'no answer'})") from None
        if r.status_code != 202:
            raise GuardUnavailable(f"the guard refused the stop ({r.status_code}: {r.text[:200]})")
        return dict(r.json())

    def close(self) -> None:
        """Stop the guard process (the devices stay as they are)."""
        self._closing = True
        end_child(self._process, self._conn, 10.0)
        self.state = "closed"
