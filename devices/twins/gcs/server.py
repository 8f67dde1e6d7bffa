"""Serve a GCS controller twin on a real TCP socket and on pseudo-terminals (serial), in a background thread.

The server runs its own asyncio loop in a daemon thread, so a twin can live
inside the same process as the driver (``sim://``), in a test, or standalone
(``orbitct twin hexapod``). A ticker keeps the simulated world current while
axes move.
"""

from __future__ import annotations

import asyncio
import os
import threading
import tty
from collections.abc import Callable
from typing import Any

from devices.gcs.framing import SINGLE_CHAR, join_reply
from devices.twins.gcs.controller import GcsController, Session

_SINGLE = {code[0]: name for name, code in SINGLE_CHAR.items()}


def split_commands(buf: bytes) -> tuple[list[str], bytes]:
    """Complete commands in ``buf`` (single-character ones as '#5', '#7', '#24') and the rest."""
    out: list[str] = []
    line = bytearray()
    rest_start = 0
    for i, b in enumerate(buf):
        if b in _SINGLE and not line:
            out.append(_SINGLE[b])
            rest_start = i + 1
        elif b == 0x0A:
            out.append(line.decode("cp1252").strip("\r"))
            line.clear()
            rest_start = i + 1
        else:
            line.append(b)
    return out, buf[rest_start:]


def garble(data: bytes) -> bytes:
    """A corrupted but complete reply (what line noise or a firmware bug might produce)."""
    body = data[:-1].replace(b" \n", b" ").replace(b"\n", b"")
    return b"%" + body[::-1] + b"\n"


class TwinServer:
    """A controller twin listening on ``host:port`` (0 = any free port) and, on request, on a pty."""

    def __init__(self, controller: GcsController, host: str = "127.0.0.1", port: int = 0) -> None:
        self.controller = controller
        self.host, self.port = host, port
        self.connections = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: asyncio.AbstractServer | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._ptys: list[tuple[int, int, str]] = []
        self._ready = threading.Event()
        self._stopping = False
        self._error: BaseException | None = None

    @property
    def faults(self) -> Any:
        """The controller's fault injector."""
        return self.controller.faults

    @property
    def uri(self) -> str:
        """``tcp://host:port`` of this twin."""
        return f"tcp://{self.host}:{self.port}"

    # ----- lifecycle -----
    def start(self) -> TwinServer:
        """Start serving in a daemon thread; returns once the socket listens."""
        self._thread = threading.Thread(target=self._run, name=f"gcs-twin-{type(self.controller).__name__}", daemon=True)
        self._thread.start()
        self._ready.wait(10.0)
        if self._error is not None:
            raise self._error
        return self

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._main())
        except BaseException as exc:  # surfaced to start()
            self._error = exc
            self._ready.set()
        finally:
            loop.close()

    async def _main(self) -> None:
        self._server = await asyncio.start_server(self._serve_tcp, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        self._ready.set()
        while not self._stopping:
            self.controller.update()
            await asyncio.sleep(0.002 if self.controller.is_moving() else 0.02)
        self._server.close()
        for w in list(self._writers):
            w.close()
        await asyncio.sleep(0.01)
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in others:
            task.cancel()
        await asyncio.gather(*others, return_exceptions=True)

    def stop(self) -> None:
        """Stop serving and close every connection and pty."""
        self._stopping = True
        if self._thread is not None:
            self._thread.join(5.0)
        for master, slave, _ in self._ptys:
            for fd in (master, slave):
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._ptys.clear()

    def call(self, fn: Callable[[], Any]) -> Any:
        """Run ``fn`` on the server's loop thread and return its result."""
        assert self._loop is not None
        done = threading.Event()
        box: list[Any] = []

        def wrapper() -> None:
            box.append(fn())
            done.set()

        self._loop.call_soon_threadsafe(wrapper)
        done.wait(5.0)
        return box[0] if box else None

    def drop_connections(self) -> None:
        """Close every open TCP connection now (a cable pulled or the controller rebooted)."""
        self.call(lambda: [w.close() for w in list(self._writers)])

    # ----- serial through a pseudo-terminal -----
    def open_serial(self) -> str:
        """Serve the controller on a new pseudo-terminal too; returns the device path for ``serial://``."""
        master, slave = os.openpty()
        tty.setraw(slave)
        path = os.ttyname(slave)
        session = Session(f"serial {path}")
        state = {"buf": b""}

        def on_readable() -> None:
            try:
                data = os.read(master, 4096)
            except OSError:
                return
            cmds, state["buf"] = split_commands(state["buf"] + data)
            for cmd in cmds:
                asyncio.ensure_future(self._answer_serial(master, session, cmd))

        self._ptys.append((master, slave, path))
        self.call(lambda: self._loop.add_reader(master, on_readable))  # type: ignore[union-attr]
        return path

    async def _answer_serial(self, master: int, session: Session, cmd: str) -> None:
        if self.faults.take_drop(cmd):  # a serial line cannot drop: the reply is lost instead
            self.controller.handle(session, cmd) if self.faults.drop_executes else None
            return
        data = self._reply_bytes(session, cmd)
        if data:
            if self.faults.latency_s:
                await asyncio.sleep(self.faults.latency_s)
            os.write(master, data)

    # ----- TCP -----
    async def _serve_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        self._writers.add(writer)
        session = Session(f"tcp {writer.get_extra_info('peername')}")
        buf = b""
        try:
            while True:
                data = await reader.read(4096)
                if not data:
                    break
                cmds, buf = split_commands(buf + data)
                for cmd in cmds:
                    if self.faults.take_drop(cmd):
                        if self.faults.drop_executes:
                            self.controller.handle(session, cmd)
                        return
                    out = self._reply_bytes(session, cmd)
                    if out:
                        if self.faults.latency_s:
                            await asyncio.sleep(self.faults.latency_s)
                        writer.write(out)
                        await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            self._writers.discard(writer)
            writer.close()

    def _reply_bytes(self, session: Session, cmd: str) -> bytes:
        reply = self.controller.handle(session, cmd)
        if reply is None:
            return b""
        data = join_reply(reply)
        return garble(data) if self.faults.take_garble() else data
