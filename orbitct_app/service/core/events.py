"""Ordered progress events per topic (``scan:<id>``, ``job:<id>``), published from any thread, streamed as SSE."""

from __future__ import annotations

import asyncio
import json
import queue
import threading
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

from orbitct_app.service.core.db import Store

FINAL_KINDS = ("end",)  # an ``end`` event closes a topic's stream


@dataclass
class _Topic:
    seq: int = 0
    recent: deque[tuple[int, str, dict[str, Any]]] = field(default_factory=lambda: deque(maxlen=2000))
    waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = field(default_factory=list)
    ended: bool = False


class EventBus:
    """Keeps each topic's events numbered in publication order; persists them to the store in the background."""

    def __init__(self, store: Store) -> None:
        self._store = store
        self._topics: dict[str, _Topic] = {}
        self._lock = threading.Lock()
        self._pending: queue.SimpleQueue[tuple[str, int, str, dict[str, Any]] | None] = queue.SimpleQueue()
        self._writer = threading.Thread(target=self._persist, name="orbitct-events", daemon=True)
        self._writer.start()

    MAX_TOPICS = 256  # ended topics beyond this many are dropped from memory (the store keeps them)

    def _topic(self, name: str) -> _Topic:
        topic = self._topics.get(name)
        if topic is None:
            if len(self._topics) >= self.MAX_TOPICS:
                for old in [k for k, t in self._topics.items() if t.ended and not t.waiters]:
                    del self._topics[old]
            seq = self._store.last_event_seq(name)
            topic = _Topic(seq=seq)
            topic.ended = any(k in FINAL_KINDS for _, k, _ in self._store.events(name, after=seq - 1)) if seq else False
            self._topics[name] = topic
        return topic

    def publish(self, topic: str, kind: str, data: dict[str, Any]) -> int:
        """Append an event (thread-safe, never blocks on I/O); returns its sequence number."""
        with self._lock:
            t = self._topic(topic)
            t.seq += 1
            seq = t.seq
            t.recent.append((seq, kind, data))
            if kind in FINAL_KINDS:
                t.ended = True
            waiters = list(t.waiters)
        self._pending.put((topic, seq, kind, data))
        for loop, ev in waiters:
            try:
                loop.call_soon_threadsafe(ev.set)
            except RuntimeError:  # that loop has closed
                pass
        return seq

    def since(self, topic: str, after: int) -> tuple[list[tuple[int, str, dict[str, Any]]], bool]:
        """Events of ``topic`` after ``after`` (memory first, then the store) and whether the topic has ended."""
        with self._lock:
            t = self._topic(topic)
            recent = [e for e in t.recent if e[0] > after]
            ended = t.ended
            complete = bool(t.recent) and t.recent[0][0] <= after + 1
        if complete or (not t.recent and after >= t.seq):
            return recent, ended
        self.flush()
        stored = self._store.events(topic, after=after)
        last = stored[-1][0] if stored else after
        return stored + [e for e in recent if e[0] > last], ended or any(k in FINAL_KINDS for _, k, _ in stored)

    def flush(self, timeout_s: float = 5.0) -> None:
        """Wait until every event published so far is in the store."""
        done = threading.Event()
        self._pending.put(("", -1, "__flush__", {"_event": done}))
        done.wait(timeout_s)

    def _persist(self) -> None:
        while True:
            item = self._pending.get()
            if item is None:
                return
            batch = [item]
            while True:
                try:
                    nxt = self._pending.get_nowait()
                except queue.Empty:
                    break
                if nxt is None:
                    self._pending.put(None)
                    break
                batch.append(nxt)
            flushes = [b[3]["_event"] for b in batch if b[2] == "__flush__"]
            rows = [b for b in batch if b[2] != "__flush__"]
            if rows:
                try:
                    self._store.add_events(rows)
                except Exception:  # noqa: BLE001 - persistence is best effort; memory keeps the stream going
                    pass
            for ev in flushes:
                ev.set()

    async def stream(
        self, topic: str, after: int = 0, keepalive_s: float = 15.0
    ) -> AsyncIterator[tuple[int, str, dict[str, Any]] | None]:
        """Yield the topic's events in order from ``after`` on, and None as a keep-alive; ends after ``end``."""
        loop = asyncio.get_running_loop()
        wake = asyncio.Event()
        with self._lock:
            self._topic(topic).waiters.append((loop, wake))
        try:
            last = after
            while True:
                wake.clear()
                events, ended = self.since(topic, last)
                for event in events:
                    last = event[0]
                    yield event
                if ended and last >= self._seq(topic):
                    return
                try:
                    await asyncio.wait_for(wake.wait(), keepalive_s)
                except TimeoutError:
                    yield None
        finally:
            with self._lock:
                waiters = self._topic(topic).waiters
                if (loop, wake) in waiters:
                    waiters.remove((loop, wake))

    def _seq(self, topic: str) -> int:
        with self._lock:
            return self._topic(topic).seq

    def close(self) -> None:
        """Persist what is pending and stop the writer thread."""
        self._pending.put(None)
        self._writer.join(timeout=5.0)


def sse_format(seq: int, kind: str, data: dict[str, Any]) -> str:
    """One server-sent event: ``id``, ``event`` and JSON ``data`` lines."""
    return f"id: {seq}\nevent: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def event_id_after(last_event_id: str | None) -> int:
    """The sequence number a ``Last-Event-ID`` header names; 0 (replay all) for anything but ASCII digits.

    ``str.isdigit`` alone would accept superscripts such as ``²`` that ``int`` refuses.
    """
    if last_event_id is None or not last_event_id.isascii() or not last_event_id.isdigit():
        return 0
    return int(last_event_id)


def sse_response(
    bus: EventBus, topic: str, last_event_id: str | None, first: tuple[str, dict[str, Any]] | None = None
) -> Any:
    """A ``text/event-stream`` response replaying ``topic`` after ``Last-Event-ID`` and following it live; ``first``:
    an event (kind, data) sent before them without an id, as the state the stream starts from."""
    from fastapi.responses import StreamingResponse

    after = event_id_after(last_event_id)

    async def _body() -> AsyncIterator[str]:
        if first is not None:
            yield f"event: {first[0]}\ndata: {json.dumps(first[1], separators=(',', ':'))}\n\n"
        async for item in bus.stream(topic, after):
            yield ": keep-alive\n\n" if item is None else sse_format(*item)

    return StreamingResponse(
        _body(), media_type="text/event-stream", headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    )
