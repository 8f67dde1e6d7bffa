"""Serve a GCS controller twin on a real TCP socket and on pseudo-terminals (serial).

:class:`GcsTwin` is a twin in the sense of :mod:`devices.twins.runtime`: run it with
:class:`~devices.twins.runtime.TwinThread`. A ticker keeps the simulated world current
while axes move.
"""

from __future__ import annotations

import asyncio
import os
import tty
from typing import ClassVar

from devices.gcs.framing import SINGLE_CHAR, join_reply
from devices.twins.gcs.controller import GcsController, Session
from devices.twins.runtime import TwinFaults, garble

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


class GcsTwin:
    """A GCS controller twin listening on TCP and, on request, on pseudo-terminals."""

    scheme: ClassVar[str] = "tcp"

    def __init__(self, controller: GcsController) -> None:
        self.controller = controller
        self.faults: TwinFaults = controller.faults
        self.connections = 0
        self._server: asyncio.AbstractServer | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._ptys: list[tuple[int, int, str]] = []
        self._answers: set[asyncio.Task[None]] = set()  # serial replies in flight (held until done)
        self._ticker: asyncio.Task[None] | None = None

    # ----- lifecycle -----
    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen on ``host:port`` (0 = any free port); returns the port."""
        self._server = await asyncio.start_server(self._serve_tcp, host, port)
        self._ticker = asyncio.ensure_future(self._tick())
        return int(self._server.sockets[0].getsockname()[1])

    async def _tick(self) -> None:
        while True:
            self.controller.update()
            await asyncio.sleep(0.002 if self.controller.is_moving() else 0.02)

    async def stop(self) -> None:
        """Stop serving and close every connection and pty."""
        if self._ticker is not None:
            self._ticker.cancel()
        if self._server is not None:
            self._server.close()
            self._server = None
        for w in list(self._writers):
            w.close()
        loop = asyncio.get_running_loop()
        for master, slave, _ in self._ptys:
            loop.remove_reader(master)
            for fd in (master, slave):
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._ptys.clear()

    def drop_connections(self) -> None:
        """Close every open TCP connection now (a cable pulled or the controller rebooted); call in the twin's loop."""
        for w in list(self._writers):
            w.close()

    # ----- serial through a pseudo-terminal -----
    def open_serial(self) -> str:
        """Serve the controller on a new pseudo-terminal too (call in the twin's loop); returns its device path."""
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
                answer = asyncio.ensure_future(self._answer_serial(master, session, cmd))
                self._answers.add(answer)
                answer.add_done_callback(self._answers.discard)

        self._ptys.append((master, slave, path))
        asyncio.get_running_loop().add_reader(master, on_readable)
        return path

    async def _answer_serial(self, master: int, session: Session, cmd: str) -> None:
        if self.faults.take("drop", cmd):  # a serial line cannot drop: the reply is lost instead
            if self.faults.drop_executes:
                self.controller.handle(session, cmd)
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
                    if self.faults.take("drop", cmd):
                        if self.faults.drop_executes:
                            self.controller.handle(session, cmd)
                        return
                    out = self._reply_bytes(session, cmd)
                    if out:
                        if self.faults.latency_s:
                            await asyncio.sleep(self.faults.latency_s)
                        writer.write(out)
                        await writer.drain()
        except (ConnectionError, OSError, asyncio.CancelledError):  # cancelled: the twin stops, the link closes
            pass
        finally:
            self._writers.discard(writer)
            writer.close()

    def _reply_bytes(self, session: Session, cmd: str) -> bytes:
        reply = self.controller.handle(session, cmd)
        if reply is None:
            return b""
        data = join_reply(reply)
        return garble(data, 0, len(data) - 1) if self.faults.take("garble", cmd) else data
