"""The stop while 100 clients poll a running scan: it is answered, proven and latched (its latency is measured in
``benchmarks/service.py``, not asserted here)."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

import httpx
import pytest

from tests.helpers.service import SMALL_SAWTOOTH, serve_subprocess, small_bench_config

pytestmark = [pytest.mark.system, pytest.mark.slow, pytest.mark.timeout(300)]
DEV = "oct_dev_token_for_the_load_test"
POLLERS = 100


async def _poll(base: str, path: str, stop: asyncio.Event, answered: list[int]) -> None:
    async with httpx.AsyncClient(base_url=base, headers={"Authorization": f"Bearer {DEV}"}, timeout=30) as client:
        while not stop.is_set():
            answered.append((await client.get(path)).status_code)
            await asyncio.sleep(0.1)


def test_stop_is_answered_and_proven_while_100_clients_poll(tmp_path: Path) -> None:
    proc, base, headers = serve_subprocess(small_bench_config(tmp_path), tmp_path / "data", DEV)
    try:
        r = httpx.post(f"{base}/scans", json={**SMALL_SAWTOOTH, "frames": 400}, headers=headers, timeout=30)
        assert r.status_code == 202, r.text
        scan_id = r.json()["id"]
        stop_url = httpx.get(f"{base}/stop", headers=headers).json()["stop_url"]
        answered: list[int] = []
        loop = asyncio.new_event_loop()
        stop = asyncio.Event()

        async def load() -> None:
            await asyncio.gather(*(_poll(base, f"/scans/{scan_id}", stop, answered) for _ in range(POLLERS)))

        thread = threading.Thread(target=lambda: loop.run_until_complete(load()), daemon=True)
        thread.start()
        while len(answered) < 5 * POLLERS:  # every poller has been answered a few times
            assert thread.is_alive()
            threading.Event().wait(0.1)
        reply = httpx.post(stop_url, headers=headers, json={"reason": "load test"}, timeout=30).json()
        loop.call_soon_threadsafe(stop.set)
        thread.join(60)
        assert reply["halted"] is True and reply["latched"] is True, reply
        assert set(answered) == {200}
        scan = httpx.get(f"{base}/scans/{scan_id}", headers=headers).json()
        while scan["state"] == "running":
            scan = httpx.get(f"{base}/scans/{scan_id}", headers=headers).json()
        assert scan["state"] == "aborted" and "load test" in scan["reason"]
    finally:
        proc.terminate()
        proc.wait(60)
