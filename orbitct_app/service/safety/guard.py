"""The guard process: a stop listener of its own and connections of its own to every device that moves or exposes.

Nothing else runs here, so a stop never queues behind status polling, a scan or a job. On
``POST /stop`` (any valid token) the guard latches the stop, then halts every device at once
over its own connections and reads each back (:func:`devices.halt.halt_and_verify`); the rig
process sees the latch and aborts its scan. The guard lives on when the rig process dies, so a
stop still reaches the devices while the rig is being restarted.

Endpoints (JSON): ``POST /stop`` (``{"reason": "..."}`` optional), ``GET /stop`` (the latch),
``GET /health`` (no token). Every reply carries ``Access-Control-Allow-Origin: *`` so a web page
served by the main port can reach the stop port.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import os
import signal
import threading
from collections.abc import Mapping
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from acquire.rigs.links import DeviceLink
from devices.halt import HaltCheck, halt_and_verify, summary
from orbitct_app.error_codes import error_kind, sentence
from orbitct_app.service.core.auth import ON_BEHALF_HEADER, Principal, TokenRegistry
from orbitct_app.service.core.settings import TokenHash
from orbitct_app.service.safety.latch import StopLatch
from orbitct_app.service.safety.request import stop_reason

LISTENER_ROUTES = "use POST /stop, GET /stop or GET /health (all the stop listener serves)"
log = logging.getLogger("orbitct.service.guard")
# what the guard connects to, with its own driver options: short time-outs, and watch-only connections where a
# second connection must not reconfigure the device (no watchdog or heartbeat on the generator, no re-arming a panel)
GUARD_OPTIONS: dict[str, dict[str, Any]] = {
    "hexapod": {"timeout_s": 1.0},
    "rotation_stage": {"timeout_s": 1.0},
    "xray": {"timeout_s": 0.5, "monitor": 1},
    "carm": {"timeout_s": 1.0, "monitor": 1},
}
HALT_TIMEOUT_S = 1.0  # per device: the stop's acknowledgement, then the read-back
RECONNECT_S = 2.0
MAX_BODY_BYTES = 4096
MAX_DRAIN_BYTES = 1 << 20  # a larger body (to any route) is refused and its connection closed


class DeviceGuard:
    """Connections of its own to the devices that move or expose, kept open in a thread; halts and verifies them."""

    def __init__(self, links: Mapping[str, DeviceLink]) -> None:
        self.links = {k: v for k, v in links.items() if k in GUARD_OPTIONS}
        self.devices: dict[str, Any] = {}
        self.problems: dict[str, str] = dict.fromkeys(self.links, "not connected yet")
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._main, name="guard-devices", daemon=True)
        self._connect_lock: asyncio.Lock | None = None

    def start(self) -> None:
        """Start the device thread; connections are made (and remade) in the background."""
        self._thread.start()

    def _main(self) -> None:
        asyncio.set_event_loop(self.loop)
        self._connect_lock = asyncio.Lock()
        self._keeper = self.loop.create_task(self._keep_connected())
        self.loop.run_forever()

    async def _connect(self, kind: str) -> None:
        from devices.factory import open_device

        assert self._connect_lock is not None
        async with self._connect_lock:
            if kind in self.devices:
                return
            link = self.links[kind]
            try:
                async with asyncio.timeout(HALT_TIMEOUT_S * 3):
                    self.devices[kind] = await open_device(kind, kind, link.uri, **GUARD_OPTIONS[kind])
                self.problems.pop(kind, None)
            except Exception as exc:  # noqa: BLE001 - reported in the next stop's reply, retried
                self.problems[kind] = f"not connected ({exc or type(exc).__name__})"

    async def _keep_connected(self) -> None:
        while True:
            for kind in self.links:
                if kind not in self.devices:
                    await self._connect(kind)
            await asyncio.sleep(RECONNECT_S)

    async def _halt(self) -> list[HaltCheck]:
        missing = [k for k in self.links if k not in self.devices]
        if missing:  # one more try, within the stop's bound
            await asyncio.gather(*(self._connect(k) for k in missing))
        checks = await halt_and_verify([self.devices[k] for k in self.links if k in self.devices], HALT_TIMEOUT_S)
        checks += [
            HaltCheck(k, False, problem=self.problems.get(k, "not connected"))
            for k in self.links
            if k not in self.devices
        ]
        return checks

    def halt(self) -> list[HaltCheck]:
        """Halt every device now and read each back (from any thread)."""
        return asyncio.run_coroutine_threadsafe(self._halt(), self.loop).result(HALT_TIMEOUT_S * 6 + 2)

    def close(self) -> None:
        """Close the connections (the devices stay as they are) and end the thread."""

        async def _close() -> None:
            self._keeper.cancel()
            for dev in self.devices.values():
                with contextlib.suppress(Exception):
                    await dev.close()

        if self._thread.is_alive():
            with contextlib.suppress(Exception):
                asyncio.run_coroutine_threadsafe(_close(), self.loop).result(5.0)
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(5.0)


class Guard:
    """The stop itself: latch first, then halt and verify; tells the web server what happened."""

    def __init__(
        self,
        devices: DeviceGuard,
        latch: StopLatch,
        tokens: TokenRegistry,
        events: Connection | None,
        forward_secret: str = "",
    ) -> None:
        self.devices, self.latch, self.tokens, self._events = devices, latch, tokens, events
        self.forward_secret = forward_secret
        self._send_lock = threading.Lock()

    def stop(self, who: Principal, reason: str) -> dict[str, Any]:
        """Latch in memory, halt every device and verify, then record the latch and answer; nothing that can fail
        (the latch file, the log, the web server's pipe) comes before the halt, and none of it stops the answer."""
        by = f"{who.name} ({who.role})"
        why = reason or f"emergency stop by {who.name}"
        self.latch.latch(by, why, via="stop listener")  # memory only: every process of the service sees it now
        checks = self.devices.halt()
        halted, message = summary(checks)
        recorded = self.latch.record()
        reply = {
            "accepted": True,
            "halted": halted,
            "latched": True,
            "message": message,
            "devices": [c.to_json() for c in checks],
            "by": by,
            "reason": why,
            "latch_recorded": recorded,
        }
        if not recorded:
            reply["latch_problem"] = f"{self.latch.record_problem}; the stop holds in memory until it is recorded"
        with contextlib.suppress(Exception):
            log.warning("emergency stop by %s: %s", by, why)
            if not halted:
                log.error("emergency stop: %s", message)
        self._tell("stopped", reply)
        return reply

    def _tell(self, *message: Any) -> None:
        if self._events is None:
            return
        with self._send_lock, contextlib.suppress(OSError, EOFError, BrokenPipeError):
            self._events.send(message)


class StopHandler(BaseHTTPRequestHandler):
    """``POST /stop``, ``GET /stop``, ``GET /health`` (HTTP/1.1, keep-alive, JSON).

    Every request is read whole (its body too, whatever its method or path) before it is answered, so that
    nothing a client sends on a keep-alive connection can be left unread and swallow the stop that follows it;
    a body that cannot be read whole (over 1 MiB, malformed, cut short) is answered 413 or 400 and its connection
    closed, except on ``POST /stop``, where the stop is taken all the same."""

    protocol_version = "HTTP/1.1"
    server_version = "orbitct-guard"
    disable_nagle_algorithm = True  # headers and body leave at once, not 40 ms apart (Nagle vs. delayed ACK)
    timeout = 30  # a connection that sends nothing for this long is closed (its thread is freed)
    guard: Guard  # set on the subclass the server uses
    raw_body = b""
    unread = ""  # why the body could not be read whole ('' when it was)

    def log_message(self, format: str, *args: Any) -> None:  # the base class's name
        log.debug("%s " + format, self.address_string(), *args)

    def handle_one_request(self) -> None:
        """One request: parse it, read its body whole, dispatch on method and path (any method: 405, not 501)."""
        try:
            self.raw_requestline = self.rfile.readline(65537)
            if len(self.raw_requestline) > 65536:
                self.requestline, self.request_version, self.command = "", "", ""
                self.send_error(414)
                self.close_connection = True
                return
            if not self.raw_requestline:
                self.close_connection = True
                return
            if not self.parse_request():  # an error was sent (and the connection is closed where it must be)
                return
            unread = self.unread = self._read_body()
            if unread:  # not read whole: the connection closes after this answer; a stop is still taken
                self.close_connection = True
                if not (self.command == "POST" and self.path.split("?")[0] == "/stop"):
                    self._error(
                        400 if unread == "malformed" else 413,
                        "bad_request" if unread == "malformed" else "request_too_large",
                        f"the request body was {unread}: it was not read, and the connection is closed",
                        "send a small JSON body (or none) in one piece",
                        close=True,
                    )
                    return
            handler = {"GET": self.do_GET, "HEAD": self.do_GET, "POST": self.do_POST, "OPTIONS": self.do_OPTIONS}.get(
                self.command
            )
            if handler is None:
                self._error(
                    405,
                    "method_not_allowed",
                    f"the stop listener does not serve {self.command[:20]!r}",
                    LISTENER_ROUTES,
                    allow="GET, HEAD, POST, OPTIONS",
                )
            else:
                handler()
            self.wfile.flush()
        except TimeoutError:
            self.close_connection = True

    def _read_body(self) -> str:
        """Read the request's body whole into ``raw_body`` (chunked or sized); what kept it from being read, or ''."""
        self.raw_body = b""
        if "chunked" in self.headers.get("Transfer-Encoding", "").lower():
            return self._read_chunked()
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            return "malformed"
        if length < 0:
            return "malformed"
        if length > MAX_DRAIN_BYTES:
            return f"over {MAX_DRAIN_BYTES} bytes"
        self.raw_body = self.rfile.read(length) if length else b""
        return "" if len(self.raw_body) == length else "cut short"

    def _read_chunked(self) -> str:
        parts: list[bytes] = []
        total = 0
        while True:
            line = self.rfile.readline(1026)
            try:
                size = int(line.split(b";")[0].strip(), 16)
            except ValueError:
                return "malformed"
            total += size
            if size < 0 or total > MAX_DRAIN_BYTES:
                return f"over {MAX_DRAIN_BYTES} bytes"
            if size == 0:
                while self.rfile.readline(65537) not in (b"\r\n", b"\n", b""):  # trailers
                    pass
                self.raw_body = b"".join(parts)
                return ""
            parts.append(self.rfile.read(size))
            self.rfile.readline(3)

    def _reply(self, status: int, body: dict[str, Any], *, allow: str = "", close: bool = False) -> None:
        data = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Access-Control-Allow-Origin", "*")
        if allow:
            self.send_header("Allow", allow)
        if close:
            self.close_connection = True
        if self.close_connection:
            self.send_header("Connection", "close")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(data)

    def _error(self, status: int, error: str, message: str, advice: str | None = None, **kw: Any) -> None:
        advice = error_kind(error).advice if advice is None else advice
        self._reply(
            status, {"error": error, "message": sentence(message, advice), "advice": advice, "details": []}, **kw
        )

    def _principal(self, permission: str) -> Principal | None:
        header = self.headers.get("Authorization", "")
        scheme, _, token = header.partition(" ")
        if scheme.lower() != "bearer" or not token or len(token) > 512:
            self._error(401, "unauthorized", "no bearer token came with the request")
            return None
        who = self.guard.tokens.authenticate(token.strip())
        behalf = self.headers.get(ON_BEHALF_HEADER, "")
        if (
            who is None
            and behalf
            and self.guard.forward_secret
            and hmac.compare_digest(token.strip().encode(), self.guard.forward_secret.encode())
        ):
            name, _, roles = behalf.partition("|")  # the web server checked this signed-in user's session
            who = Principal.from_label(name[:100], roles[:60])
        if who is None:
            self._error(401, "unauthorized", "unknown token")
            return None
        if not who.may(permission):
            self._error(403, "forbidden", who.refusal(permission), who.refusal_advice(permission))
            return None
        return who

    def do_POST(self) -> None:  # http.server's naming
        if self.path.split("?")[0] != "/stop":
            self._error(404, "not_found", f"the stop listener has no {self.path[:60]!r}", LISTENER_ROUTES)
            return
        who = self._principal("stop")
        if who is None:
            return
        too_long = len(self.raw_body) > MAX_BODY_BYTES
        reason, problem = stop_reason(b"" if too_long else self.raw_body)
        if too_long:
            problem = f"the body was over {MAX_BODY_BYTES} bytes"
        if self.unread:
            problem = f"the body was {self.unread} and was not read"
        reply = self.guard.stop(who, reason)  # a malformed body never keeps a stop from being taken
        if problem:
            reply["note"] = f"{problem}; the stop was taken"
        self._reply(202, reply)

    def do_GET(self) -> None:
        path = self.path.split("?")[0]
        if path == "/health":
            self._reply(200, {"status": "ok", "latched": self.guard.latch.latched})
        elif path == "/stop":
            if self._principal("read") is not None:
                self._reply(200, self.guard.latch.state())
        else:
            self._error(404, "not_found", f"the stop listener has no {self.path[:60]!r}", LISTENER_ROUTES)

    def do_OPTIONS(self) -> None:  # CORS pre-flight of a browser's stop button
        self.send_response(204)
        self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Access-Control-Allow-Methods", "GET, POST, OPTIONS")
        self.send_header("Access-Control-Allow-Headers", "Authorization, Content-Type")
        self.send_header("Access-Control-Max-Age", "600")
        self.send_header("Content-Length", "0")
        self.end_headers()


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    request_queue_size = 128


def guard_main(
    links: dict[str, tuple[str, dict[str, Any]]],
    data_dir: str,
    flag: Any,
    host: str,
    port: int,
    tokens: list[dict[str, Any]],
    tokens_path: str | None,
    dev_token: str | None,
    conn: Connection,
    nice: int = 0,
    forward_secret: str = "",
) -> None:
    """Entry point of the guard process: listen on ``host:port`` (0: any free port), report the port, serve."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s guard: %(message)s")
    if nice < 0:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, nice)
    registry = TokenRegistry(
        [TokenHash.model_validate(t) for t in tokens], Path(tokens_path) if tokens_path else None, dev_token
    )
    devices = DeviceGuard({k: DeviceLink(*v) for k, v in links.items()})
    guard = Guard(devices, StopLatch(Path(data_dir), flag), registry, conn, forward_secret)
    handler = type("BoundStopHandler", (StopHandler,), {"guard": guard})
    try:
        server = _Server((host, port), handler)
    except OSError as exc:
        guard._tell("failed", f"cannot listen on {host}:{port} ({exc.strerror or exc})")
        return
    devices.start()
    guard._tell("ready", server.server_address[1])

    def _watch_parent() -> None:  # the web server's end of the pipe closes when it exits: so does the guard
        with contextlib.suppress(EOFError, OSError):
            while conn.recv() != "shutdown":
                pass
        server.shutdown()

    threading.Thread(target=_watch_parent, name="guard-parent", daemon=True).start()
    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        # Ctrl-C and systemctl signal every process of the service at once: the guard keeps taking stops
        # while the service shuts down, and ends when the web server has (its pipe closes)
        signal.signal(sig, signal.SIG_IGN)
    try:
        server.serve_forever(poll_interval=0.1)
    finally:
        server.server_close()
        devices.close()
