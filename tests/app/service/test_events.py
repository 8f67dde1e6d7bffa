"""Events per topic: numbered in publication order, replayed after an id, kept across a restart."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st

from orbitct_app.service.core.db import Store
from orbitct_app.service.core.events import EventBus, event_id_after


@given(st.text(max_size=30))
def test_any_last_event_id_header_parses_to_a_sequence_number(header: str) -> None:
    after = event_id_after(header)
    assert isinstance(after, int) and after >= 0
    assert after == (int(header) if header.isascii() and header.isdigit() else 0)


def test_events_from_many_threads_keep_one_order(tmp_path: Path) -> None:
    bus = EventBus(Store(tmp_path / "e.sqlite"))

    def pub(k: int) -> None:
        for i in range(200):
            bus.publish("scan:x", "progress", {"thread": k, "i": i})

    threads = [threading.Thread(target=pub, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    events, ended = bus.since("scan:x", 0)
    assert [e[0] for e in events] == list(range(1, 801)) and not ended
    for k in range(4):  # each publisher's own events stay in its order
        assert [e[2]["i"] for e in events if e[2]["thread"] == k] == list(range(200))
    bus.close()


def test_stream_follows_live_and_ends(tmp_path: Path) -> None:
    bus = EventBus(Store(tmp_path / "e.sqlite"))

    async def consume() -> list[int]:
        seen = []
        async for item in bus.stream("job:j", after=0, keepalive_s=0.05):
            if item is not None:
                seen.append(item[0])
        return seen

    def produce() -> None:
        for i in range(50):
            bus.publish("job:j", "progress", {"i": i})
        bus.publish("job:j", "end", {"state": "succeeded"})

    async def main() -> list[int]:
        task = asyncio.create_task(consume())
        await asyncio.sleep(0.01)
        await asyncio.to_thread(produce)
        return await asyncio.wait_for(task, 5)

    assert asyncio.run(main()) == list(range(1, 52))
    bus.close()


def test_history_survives_a_new_bus(tmp_path: Path) -> None:
    store = Store(tmp_path / "e.sqlite")
    bus = EventBus(store)
    for i in range(3):
        bus.publish("scan:s", "progress", {"i": i})
    bus.publish("scan:s", "end", {"state": "complete"})
    bus.close()
    bus2 = EventBus(Store(tmp_path / "e.sqlite"))
    events, ended = bus2.since("scan:s", 1)
    assert [e[0] for e in events] == [2, 3, 4] and ended
    assert bus2.publish("scan:s", "note", {}) == 5  # numbering continues
    bus2.close()
