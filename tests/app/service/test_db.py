"""Schema migrations and the restart bookkeeping of the SQLite store."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from orbitct_app.service.core.db import SCHEMA_VERSION, Store, StoreError


def test_fresh_database_is_at_latest_version(tmp_path: Path) -> None:
    store = Store(tmp_path / "a.sqlite")
    assert store.version() == SCHEMA_VERSION
    assert store.migrate() == SCHEMA_VERSION  # idempotent


def _store_at_version(path: Path, version: int) -> Store:
    """A store at ``path`` migrated only up to schema ``version``, as an older release left it."""
    import threading

    store = Store.__new__(Store)
    store.path = path
    store._local, store._write_lock = threading.local(), threading.Lock()
    assert store.migrate(target=version) == version
    return store


def test_old_database_migrates_and_keeps_its_rows(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite"
    s1 = _store_at_version(path, 1)  # a database of schema version 1, as the first release wrote it
    s1._conn().execute(
        "INSERT INTO scans (id, name, state, orbit, request_json, file, owner, created_utc) "
        "VALUES ('s1', 'old', 'complete', 'circular', '{}', 'scans/s1.h5', 'me', '2026-01-01')"
    )
    s1.close()
    s2 = Store(path)
    assert s2.version() == SCHEMA_VERSION
    row = s2.get_scan("s1")
    assert row["name"] == "old" and row["progress"] == {}
    s2.add_events([("scan:s1", 1, "state", {"state": "complete"})])
    assert s2.events("scan:s1") == [(1, "state", {"state": "complete"})]


def test_newer_database_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "new.sqlite"
    Store(path).close()
    conn = sqlite3.connect(path)
    conn.execute("INSERT INTO schema_version VALUES (?)", (SCHEMA_VERSION + 5,))
    conn.commit()
    conn.close()
    with pytest.raises(StoreError, match="newer"):
        Store(path)


def test_mark_interrupted(tmp_path: Path) -> None:
    store = Store(tmp_path / "c.sqlite")
    store.add_scan("s1", name="", orbit="circular", request={}, file="scans/s1.h5", owner="o", frames_total=5)
    store.update_scan("s1", state="running")
    store.add_scan("s2", name="", orbit="circular", request={}, file="scans/s2.h5", owner="o", frames_total=5)
    store.update_scan("s2", state="complete")
    store.add_job("j1", kind="calibration", scan_id="s2", params={}, owner="a")
    store.update_job("j1", state="running")
    store.add_job("j2", kind="calibration", scan_id="s2", params={}, owner="a")
    scans, jobs = store.mark_interrupted("service restarted")
    assert scans == ["s1"] and jobs == ["j1"]
    assert store.get_scan("s1")["state"] == "interrupted" and store.get_scan("s1")["reason"] == "service restarted"
    assert store.get_scan("s2")["state"] == "complete"
    assert store.get_job("j1")["state"] == "interrupted" and store.get_job("j2")["state"] == "queued"
    assert store.get_job("j1")["error"] == "interrupted" and store.get_job("j2")["error"] == ""


def test_jobs_that_ended_before_error_codes_get_theirs(tmp_path: Path) -> None:
    """A database of schema version 3 (jobs without error codes): its failed and interrupted jobs get the codes."""
    path = tmp_path / "v3.sqlite"
    s3 = _store_at_version(path, 3)
    conn = s3._conn()
    conn.execute(
        "INSERT INTO scans (id, name, state, orbit, request_json, file, owner, created_utc) "
        "VALUES ('s1', 'old', 'complete', 'circular', '{}', 'scans/s1.h5', 'me', '2026-01-01')"
    )
    for job, state, result in (
        ("quality", "failed", '{"verdict": {"status": "failed"}}'),
        ("crashed", "failed", "{}"),
        ("stopped", "interrupted", "{}"),
        ("fine", "succeeded", '{"verdict": {"status": "passed"}}'),
    ):
        conn.execute(
            "INSERT INTO jobs (id, kind, scan_id, state, params_json, owner, created_utc, result_json) "
            "VALUES (?, 'calibration', 's1', ?, '{}', 'me', '2026-01-01', ?)",
            (job, state, result),
        )
    s3.close()
    store = Store(path)
    codes = {job: store.get_job(job)["error"] for job in ("quality", "crashed", "stopped", "fine")}
    assert codes == {
        "quality": "failed_quality_check",
        "crashed": "action_failed",
        "stopped": "interrupted",
        "fine": "",
    }
