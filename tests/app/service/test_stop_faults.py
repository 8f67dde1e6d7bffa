"""The stop and the service under faults of the data directory: a full disk, a read-only filesystem, a database locked
by another program. Every stop path (the guard's listener, ``POST /stop``, ``orbitct stop``) halts the axes and
switches X-rays off (read back from the twins over the test's own connections), answers, and the latch holds; the
scan's record ends with its true state; once the cause is gone the service records what it kept in memory and takes
a new scan without a restart."""

from __future__ import annotations

import json
import sqlite3
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from click.testing import CliRunner

from orbitct_app.cli.main import cli
from tests.helpers.service import SMALL_SAWTOOTH, ended, small_bench_config, wait_for
from tests.helpers.smallfs import failing_filesystem, fill, small_filesystem
from tests.helpers.twin_readback import twins_halted

pytestmark = [pytest.mark.system, pytest.mark.timeout(300)]
MB = 1 << 20


def _config(folder: Path) -> Path:
    folder.mkdir(exist_ok=True)
    path = small_bench_config(folder, size=128)
    cfg = yaml.safe_load(path.read_text())
    cfg["storage"] = {"reserve_mb": 2.0}
    path.write_text(yaml.safe_dump(cfg))
    return path


def _scan_running(api: Any, frames: int = 400) -> str:
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": frames})
    assert r.status_code == 202, r.text
    scan_id = str(r.json()["id"])
    wait_for(api, f"/scans/{scan_id}", lambda b: b["progress"].get("done", 0) >= 5 or ended(b), 60)
    return scan_id


def _assert_halted(api: Any, reply: dict[str, Any]) -> None:
    assert reply["halted"] is True and reply["latched"] is True, reply
    readback = twins_halted(api.service.sim_bench.links)
    assert set(readback) == {"hexapod", "rotation_stage", "xray"} and all(ok for ok, _ in readback.values()), readback


def _guard_stop(api: Any, reason: str) -> dict[str, Any]:
    r = httpx.post(api.service.guard.url + "/stop", headers=api.headers("viewer"), json={"reason": reason}, timeout=10)
    assert r.status_code == 202, r.text
    return dict(r.json())


def _cli_stop(api: Any) -> tuple[int, str]:
    base = "http://127.0.0.1:1"  # the service's own port is a test client's: the CLI goes to the guard's listener
    result = CliRunner().invoke(
        cli,
        [
            "stop",
            "--url",
            base,
            "--token",
            api.tokens["viewer"],
            "--stop-url",
            api.service.guard.url + "/stop",
            "--reason",
            "cli drill",
        ],
    )
    return result.exit_code, result.output


def _back_to_work(api: Any) -> None:
    """The causes are gone: the latch and the scan records are written, a reset is taken, a new scan completes."""
    wait_for(api, "/stop", lambda b: b["recorded"] is True, 30, poll_s=0.2)
    assert json.loads((api.data_dir / "estop.json").read_text())["latched"] is True
    t0 = time.monotonic()
    while api.service.store.pending_writes() and time.monotonic() - t0 < 30:
        time.sleep(0.2)
    assert api.service.store.pending_writes() == 0, api.service.store.write_problem
    r = api.post("/stop/reset", json={"note": "disk checked"})
    assert r.status_code == 200 and r.json()["latched"] is False and r.json()["recorded"] is True, r.text
    r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 12})
    assert r.status_code == 202, r.text
    assert wait_for(api, f"/scans/{r.json()['id']}", ended, 90)["state"] == "complete"


def test_full_disk_every_stop_path_halts_answers_and_latches(make_api, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    with small_filesystem(tmp_path / "disk", 40) as disk:
        api = make_api(data_dir=disk / "data", bench_config=_config(tmp_path / "config"))
        scan_id = _scan_running(api)
        filler = fill(disk, leave_bytes=0)  # not a byte left: neither the latch file nor the database can be written

        reply = _guard_stop(api, "disk full drill")
        _assert_halted(api, reply)
        assert reply["latch_recorded"] is False and "No space left" in reply["latch_problem"], reply
        state = api.get("/stop").json()
        assert state["latched"] and state["by"] == "test-viewer (viewer)" and state["reason"] == "disk full drill"
        assert state["recorded"] is False

        r = api.post("/stop", role="viewer", json={"reason": "second stop"})
        assert r.status_code == 202, r.text
        _assert_halted(api, r.json())
        code, out = _cli_stop(api)
        assert code == 0 and out.startswith("HALTED"), out

        scan = wait_for(api, f"/scans/{scan_id}", ended, 60)  # ended in memory: the database cannot take it yet
        assert scan["state"] == "aborted" and ("emergency stop" in scan["reason"] or "disk" in scan["reason"]), scan
        assert api.service.rig.busy is None
        refused = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4})
        assert refused.status_code in (409, 507) and "Traceback" not in refused.text

        filler.unlink()
        _back_to_work(api)
        assert api.service.store.get_scan(scan_id)["state"] == "aborted"


def test_read_only_data_directory_stop_halts_and_the_service_recovers(make_api, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    with failing_filesystem(tmp_path / "disk", 64) as fs:
        api = make_api(data_dir=fs.path / "data", bench_config=_config(tmp_path / "config"))
        scan_id = _scan_running(api)
        fs.turn_read_only()  # a disk error: the kernel turns the data's filesystem read-only under the running scan

        reply = _guard_stop(api, "read-only drill")
        _assert_halted(api, reply)
        assert reply["latch_recorded"] is False and "Read-only" in reply["latch_problem"], reply
        scan = wait_for(api, f"/scans/{scan_id}", ended, 60)
        assert scan["state"] == "aborted", scan
        r = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4})
        assert r.status_code in (409, 503, 507) and "Traceback" not in r.text, r.text

        fs.repair()  # the operator checks the disk and mounts it again
        _back_to_work(api)
        assert api.service.store.get_scan(scan_id)["state"] == "aborted"


def test_locked_database_stop_halts_the_scan_ends_and_the_service_recovers(make_api, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    api = make_api(bench_config=_config(tmp_path / "config"))
    scan_id = _scan_running(api)
    other = sqlite3.connect(api.service.store.path, isolation_level=None, timeout=0.1)  # another program's lock
    other.execute("BEGIN EXCLUSIVE")
    other.execute("UPDATE scans SET name = name")
    try:
        r = api.post("/stop", role="viewer", json={"reason": "locked database drill"})
        assert r.status_code == 202, r.text
        _assert_halted(api, r.json())
        scan = wait_for(api, f"/scans/{scan_id}", ended, 60)
        assert scan["state"] == "aborted" and "locked database drill" in scan["reason"], scan
        assert api.service.rig.busy is None
        assert api.service.store.pending_writes() >= 1 and "locked" in (api.service.store.write_problem or "")
        refused = api.post("/scans", json={**SMALL_SAWTOOTH, "frames": 4})
        assert refused.status_code in (409, 503) and "Traceback" not in refused.text
    finally:
        other.execute("ROLLBACK")
        other.close()
    _back_to_work(api)
    assert api.service.store.get_scan(scan_id)["state"] == "aborted"
