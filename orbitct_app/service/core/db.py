"""SQLite store of scans, jobs, job logs and progress events, with versioned schema migrations."""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterable, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

# Each entry moves the schema from version i to i + 1; never edit a released entry, append a new one.
MIGRATIONS: tuple[str, ...] = (
    """
    CREATE TABLE scans (
        id TEXT PRIMARY KEY, name TEXT NOT NULL, state TEXT NOT NULL, reason TEXT NOT NULL DEFAULT '',
        orbit TEXT NOT NULL, request_json TEXT NOT NULL, file TEXT NOT NULL, owner TEXT NOT NULL,
        created_utc TEXT NOT NULL, started_utc TEXT, finished_utc TEXT,
        frames_done INTEGER NOT NULL DEFAULT 0, frames_total INTEGER NOT NULL DEFAULT 0,
        summary_json TEXT NOT NULL DEFAULT '{}'
    );
    CREATE TABLE jobs (
        id TEXT PRIMARY KEY, kind TEXT NOT NULL, scan_id TEXT NOT NULL REFERENCES scans(id),
        state TEXT NOT NULL, reason TEXT NOT NULL DEFAULT '', params_json TEXT NOT NULL, owner TEXT NOT NULL,
        created_utc TEXT NOT NULL, started_utc TEXT, finished_utc TEXT,
        progress_json TEXT NOT NULL DEFAULT '{}', result_json TEXT NOT NULL DEFAULT '{}'
    );
    CREATE INDEX jobs_scan ON jobs(scan_id);
    """,
    """
    CREATE TABLE job_log (
        job_id TEXT NOT NULL REFERENCES jobs(id), seq INTEGER NOT NULL, time_utc TEXT NOT NULL, line TEXT NOT NULL,
        PRIMARY KEY (job_id, seq)
    );
    CREATE TABLE events (
        topic TEXT NOT NULL, seq INTEGER NOT NULL, kind TEXT NOT NULL, data_json TEXT NOT NULL,
        PRIMARY KEY (topic, seq)
    );
    """,
    """
    ALTER TABLE scans ADD COLUMN progress_json TEXT NOT NULL DEFAULT '{}';
    """,
)
SCHEMA_VERSION = len(MIGRATIONS)
RUNNING_SCAN_STATES = ("queued", "running", "paused")


class StoreError(RuntimeError):
    """The database cannot be opened or migrated."""


def utc_now() -> str:
    """Current UTC time, ISO 8601 with seconds."""
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def _row(row: sqlite3.Row | None) -> dict[str, Any] | None:
    if row is None:
        return None
    out = dict(row)
    for key in list(out):
        if key.endswith("_json"):
            out[key[:-5]] = json.loads(out.pop(key))
    return out


class Store:
    """Thread-safe access to the service database (one connection per thread, WAL journal)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        self._write_lock = threading.Lock()
        self.migrate()

    def _conn(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = sqlite3.connect(self.path, timeout=10.0, isolation_level=None, check_same_thread=False)
            conn.row_factory = sqlite3.Row
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
            conn.execute("PRAGMA foreign_keys=ON")
            self._local.conn = conn
        return conn

    # ----------------------------------------------------------- migrations
    def version(self) -> int:
        """Schema version of the database file."""
        conn = self._conn()
        conn.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
        row = conn.execute("SELECT MAX(version) FROM schema_version").fetchone()
        return int(row[0] or 0)

    def migrate(self, target: int = SCHEMA_VERSION) -> int:
        """Apply the missing migrations up to ``target``, each in one transaction; returns the version."""
        with self._write_lock:
            current = self.version()
            if current > SCHEMA_VERSION:
                raise StoreError(f"{self.path}: schema version {current} is newer than this software ({SCHEMA_VERSION})")
            conn = self._conn()
            for version in range(current, min(target, SCHEMA_VERSION)):
                try:
                    conn.execute("BEGIN IMMEDIATE")
                    for statement in MIGRATIONS[version].split(";"):
                        if statement.strip():
                            conn.execute(statement)
                    conn.execute("INSERT INTO schema_version (version) VALUES (?)", (version + 1,))
                    conn.execute("COMMIT")
                except sqlite3.Error as exc:
                    conn.execute("ROLLBACK")
                    raise StoreError(f"{self.path}: migration to version {version + 1} failed ({exc})") from None
            return self.version()

    def _write(self, sql: str, args: Sequence[Any] = ()) -> int:
        with self._write_lock:
            return self._conn().execute(sql, args).rowcount

    # ---------------------------------------------------------------- scans
    def add_scan(self, scan_id: str, *, name: str, orbit: str, request: dict[str, Any], file: str, owner: str, frames_total: int) -> None:
        """Record a new scan in state ``queued``."""
        self._write(
            "INSERT INTO scans (id, name, state, orbit, request_json, file, owner, created_utc, frames_total) "
            "VALUES (?, ?, 'queued', ?, ?, ?, ?, ?, ?)",
            (scan_id, name, orbit, json.dumps(request), file, owner, utc_now(), frames_total),
        )

    def update_scan(self, scan_id: str, **fields: Any) -> None:
        """Set columns of a scan (``summary``/``progress`` are stored as JSON)."""
        self._update("scans", scan_id, fields)

    def delete_scan(self, scan_id: str) -> None:
        """Forget a scan that never started (and has no jobs)."""
        self._write("DELETE FROM scans WHERE id = ? AND NOT EXISTS (SELECT 1 FROM jobs WHERE scan_id = ?)", (scan_id, scan_id))

    def get_scan(self, scan_id: str) -> dict[str, Any] | None:
        """One scan, or None."""
        return _row(self._conn().execute("SELECT * FROM scans WHERE id = ?", (scan_id,)).fetchone())

    def list_scans(self, *, state: str | None = None, limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        """Scans, newest first."""
        sql, args = "SELECT * FROM scans", []
        if state is not None:
            sql, args = sql + " WHERE state = ?", [state]
        rows = self._conn().execute(sql + " ORDER BY rowid DESC LIMIT ? OFFSET ?", (*args, limit, offset))
        return [r for r in map(_row, rows.fetchall()) if r is not None]

    # ----------------------------------------------------------------- jobs
    def add_job(self, job_id: str, *, kind: str, scan_id: str, params: dict[str, Any], owner: str) -> None:
        """Record a new job in state ``queued``."""
        self._write(
            "INSERT INTO jobs (id, kind, scan_id, state, params_json, owner, created_utc) VALUES (?, ?, ?, 'queued', ?, ?, ?)",
            (job_id, kind, scan_id, json.dumps(params), owner, utc_now()),
        )

    def update_job(self, job_id: str, **fields: Any) -> None:
        """Set columns of a job (``progress``/``result``/``params`` are stored as JSON)."""
        self._update("jobs", job_id, fields)

    def get_job(self, job_id: str) -> dict[str, Any] | None:
        """One job, or None."""
        return _row(self._conn().execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone())

    def list_jobs(self, *, kind: str | None = None, scan_id: str | None = None, state: str | None = None,
                  limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        """Jobs, newest first, filtered."""
        where, args = [], []
        for column, value in (("kind", kind), ("scan_id", scan_id), ("state", state)):
            if value is not None:
                where.append(f"{column} = ?")
                args.append(value)
        sql = "SELECT * FROM jobs" + (" WHERE " + " AND ".join(where) if where else "")
        rows = self._conn().execute(sql + " ORDER BY rowid DESC LIMIT ? OFFSET ?", (*args, limit, offset))
        return [r for r in map(_row, rows.fetchall()) if r is not None]

    def queued_jobs(self) -> list[dict[str, Any]]:
        """Jobs waiting for a worker, oldest first."""
        rows = self._conn().execute("SELECT * FROM jobs WHERE state = 'queued' ORDER BY rowid").fetchall()
        return [r for r in map(_row, rows) if r is not None]

    def add_log(self, job_id: str, lines: Iterable[str]) -> None:
        """Append lines to a job's log."""
        with self._write_lock:
            conn = self._conn()
            row = conn.execute("SELECT COALESCE(MAX(seq), 0) FROM job_log WHERE job_id = ?", (job_id,)).fetchone()
            start = int(row[0])
            conn.executemany(
                "INSERT INTO job_log (job_id, seq, time_utc, line) VALUES (?, ?, ?, ?)",
                [(job_id, start + i + 1, utc_now(), line[:2000]) for i, line in enumerate(lines)],
            )

    def job_log(self, job_id: str, *, after: int = 0, limit: int = 1000) -> list[dict[str, Any]]:
        """Log lines of a job after sequence number ``after``."""
        rows = self._conn().execute(
            "SELECT seq, time_utc, line FROM job_log WHERE job_id = ? AND seq > ? ORDER BY seq LIMIT ?", (job_id, after, limit)
        )
        return [dict(r) for r in rows.fetchall()]

    # --------------------------------------------------------------- events
    def add_events(self, events: Iterable[tuple[str, int, str, dict[str, Any]]]) -> None:
        """Store ``(topic, seq, kind, data)`` events (duplicates are ignored)."""
        with self._write_lock:
            self._conn().executemany(
                "INSERT OR IGNORE INTO events (topic, seq, kind, data_json) VALUES (?, ?, ?, ?)",
                [(t, s, k, json.dumps(d)) for t, s, k, d in events],
            )

    def events(self, topic: str, *, after: int = 0, limit: int = 10_000) -> list[tuple[int, str, dict[str, Any]]]:
        """Stored events of ``topic`` after ``after``, in order."""
        rows = self._conn().execute(
            "SELECT seq, kind, data_json FROM events WHERE topic = ? AND seq > ? ORDER BY seq LIMIT ?", (topic, after, limit)
        )
        return [(int(s), k, json.loads(d)) for s, k, d in rows.fetchall()]

    def last_event_seq(self, topic: str) -> int:
        """Highest stored sequence number of ``topic`` (0 if none)."""
        row = self._conn().execute("SELECT COALESCE(MAX(seq), 0) FROM events WHERE topic = ?", (topic,)).fetchone()
        return int(row[0])

    # ------------------------------------------------------------- recovery
    def mark_interrupted(self, reason: str) -> tuple[list[str], list[str]]:
        """Mark scans and jobs left running by a previous process as interrupted; returns their ids."""
        with self._write_lock:
            conn = self._conn()
            q = ",".join("?" * len(RUNNING_SCAN_STATES))
            scans = [r[0] for r in conn.execute(f"SELECT id FROM scans WHERE state IN ({q})", RUNNING_SCAN_STATES)]
            jobs = [r[0] for r in conn.execute("SELECT id FROM jobs WHERE state = 'running'")]
            now = utc_now()
            conn.execute(f"UPDATE scans SET state = 'interrupted', reason = ?, finished_utc = ? WHERE state IN ({q})",
                         (reason, now, *RUNNING_SCAN_STATES))
            conn.execute("UPDATE jobs SET state = 'interrupted', reason = ?, finished_utc = ? WHERE state = 'running'", (reason, now))
        return scans, jobs

    def _update(self, table: str, row_id: str, fields: dict[str, Any]) -> None:
        if not fields:
            return
        cols, args = [], []
        for key, value in fields.items():
            if key in ("summary", "progress", "result", "params", "request"):
                key, value = key + "_json", json.dumps(value)
            if not key.replace("_", "").isalnum():
                raise StoreError(f"bad column name {key!r}")
            cols.append(f"{key} = ?")
            args.append(value)
        self._write(f"UPDATE {table} SET {', '.join(cols)} WHERE id = ?", (*args, row_id))

    def close(self) -> None:
        """Close this thread's connection."""
        conn = getattr(self._local, "conn", None)
        if conn is not None:
            conn.close()
            self._local.conn = None
