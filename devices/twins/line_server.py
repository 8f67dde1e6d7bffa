"""The frame-protocol server (:mod:`devices.frame_protocol`) that the detector and C-arm twins build on.

Command lines in, ``OK``/``ERR`` lines and frames out; a command ``VERB`` is served by a method
``cmd_verb`` (``?`` becomes ``_q``); faults (:class:`~devices.twins.runtime.TwinFaults`) on request.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import time
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from devices.frame_protocol import ERR_BAD_ARG, ERR_DEVICE, ERR_NO_FRAME, ERR_UNKNOWN, Frame, encode_frame
from devices.twins.runtime import TwinFaults, garble


class CommandError(Exception):
    """A command the twin refuses: becomes ``ERR <code> <text>``."""

    def __init__(self, code: int, text: str) -> None:
        super().__init__(text)
        self.code, self.text = code, text


class LineTwinServer:
    """TCP server of the frame protocol: command lines in, ``OK``/``ERR`` lines and frames out, faults on request."""

    scheme: ClassVar[str] = "tcp"

    model = "orbitct twin"
    serial = "0000"
    firmware = "1.0"

    def __init__(self) -> None:
        self.faults = TwinFaults()
        self.frames: asyncio.Queue[Frame | str] | None = None  # a str reports a frame that failed
        self.frame_number = 0
        self.commands_seen: list[str] = []
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task[Any]] = set()

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen on ``host:port`` (0 = any free port); returns the port."""
        self.frames = asyncio.Queue()
        self._server = await asyncio.start_server(self._serve, host, port)
        await self.started()
        return int(self._server.sockets[0].getsockname()[1])

    async def started(self) -> None:
        """Hook for subclasses (background tasks)."""

    async def stop(self) -> None:
        """Close every connection and the listener."""
        for task in list(self._tasks):
            task.cancel()
        for w in list(self._writers):
            w.close()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None

    def spawn(self, coro: Any) -> asyncio.Task[Any]:
        """Run a background task that :meth:`stop` cancels."""
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def drop_connections(self) -> None:
        """Close every client connection now."""
        for w in list(self._writers):
            w.transport.abort()

    # ---------------------------------------------------------------- frames
    def next_number(self) -> int:
        """Number for a frame being taken now."""
        self.frame_number += 1
        return self.frame_number

    def push_frame(
        self, number: int, data: NDArray[np.uint16], kind: str, meta: dict[str, Any], timestamp: float | None = None
    ) -> None:
        """Queue frame ``number`` taken at ``timestamp`` (default now), unless a missing-frame fault swallows it."""
        if self.faults.take("missing_frame", f"frame {number};"):
            return
        assert self.frames is not None
        self.frames.put_nowait(
            Frame(np.asarray(data, np.uint16), number, time.time() if timestamp is None else timestamp, kind, meta)
        )

    def clear_frames(self) -> None:
        """Discard queued frames."""
        assert self.frames is not None
        while not self.frames.empty():
            self.frames.get_nowait()

    async def cmd_frame_q(self, args: list[str]) -> bytes:
        """``FRAME? ms``: the next queued frame, waiting up to ``ms``."""
        timeout_ms = int_arg(args, 0, default=0)
        assert self.frames is not None
        try:
            frame = (
                await asyncio.wait_for(self.frames.get(), timeout_ms / 1000.0)
                if timeout_ms
                else self.frames.get_nowait()
            )
        except (TimeoutError, asyncio.QueueEmpty):
            raise CommandError(ERR_NO_FRAME, f"no frame within {timeout_ms} ms") from None
        if isinstance(frame, str):
            raise CommandError(ERR_DEVICE, frame)
        return encode_frame(frame)

    async def cmd_idn_q(self, args: list[str]) -> str:
        """``IDN?``: model, serial, firmware."""
        return f"{self.model},{self.serial},{self.firmware}"

    # ---------------------------------------------------------------- serving
    def _handler(self, verb: str) -> Callable[[list[str]], Any] | None:
        name = "cmd_" + verb.lower().replace("?", "_q")
        fn = getattr(self, name, None)
        return fn if callable(fn) and name.startswith("cmd_") else None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        try:
            while True:
                raw = await reader.readline()
                if not raw:
                    break
                line = raw.decode("latin-1").strip()
                if not line:
                    continue
                self.commands_seen.append(line)
                if self.faults.latency_s > 0:
                    await asyncio.sleep(self.faults.latency_s)
                if self.faults.take("drop", line):
                    writer.transport.abort()
                    break
                reply = await self._dispatch(line)
                if self.faults.take("garble", line):
                    end = reply.find(b"\n")
                    reply = garble(reply, 0, end if end >= 0 else len(reply))  # the reply line; its LF stays
                writer.write(reply)
                await writer.drain()
        except (ConnectionError, OSError, asyncio.CancelledError):  # cancelled: the twin stops, the link closes
            pass
        finally:
            self._writers.discard(writer)
            writer.close()

    async def _dispatch(self, line: str) -> bytes:
        verb, *args = line.split()
        if self.faults.take("error", line):
            return f"ERR {ERR_DEVICE} injected device error on {verb}\n".encode()
        fn = self._handler(verb)
        if fn is None:
            return f"ERR {ERR_UNKNOWN} unknown command {verb!r}\n".encode()
        try:
            result = fn(args)
            if inspect.isawaitable(result):
                result = await result
        except CommandError as exc:
            return f"ERR {exc.code} {exc.text}\n".encode()
        if isinstance(result, bytes):
            return result
        return (f"OK {result}" if result else "OK").encode() + b"\n"


def int_arg(args: list[str], i: int, *, default: int | None = None) -> int:
    """Argument ``i`` as an integer (``default`` when absent); ``ERR 4`` otherwise."""
    try:
        return int(args[i])
    except IndexError:
        if default is not None:
            return default
        raise CommandError(ERR_BAD_ARG, "missing integer argument") from None
    except ValueError:
        raise CommandError(ERR_BAD_ARG, f"not an integer: {args[i]!r}") from None
