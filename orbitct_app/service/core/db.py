"""SQLite store of scans, jobs, job logs and progress events, with versioned schema migrations.

A write that the database refuses for a cause outside the service (a full disk, a read-only data directory,
a lock held by another program) raises :class:`StoreUnavailable` with that cause in words; updates of existing
scans and jobs (a scan's end, a job's end, progress) and log lines are not lost that way: they are kept in
memory, shown by every read, and written once the cause is gone (retried in the background).
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime
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
    """
    ALTER TABLE jobs ADD COLUMN error TEXT NOT NULL DEFAULT '';
    UPDATE jobs SET error = 'failed_quality_check'
        WHERE state = 'failed' AND json_extract(result_json, '$.verdict.status') = 'failed';
    UPDATE jobs SET error = 'action_failed' WHERE state = 'failed' AND error = '';
    UPDATE jobs SET error = 'interrupted' WHERE state = 'interrupted';
    """,
)
SCHEMA_VERSION = len(MIGRATIONS)
RUNNING_SCAN_STATES = ("queued", "running", "paused")


log = logging.getLogger("orbitct.service.db")
RETRY_S = 1.0  # pause between tries to write the updates kept in memory


class StoreError(RuntimeError):
    """The database cannot be opened or migrated."""


class StoreUnavailable(StoreError):
    """The database cannot be written now, for a cause outside the service (the message says which)."""

    def __init__(self, message: str, *, disk_full: bool = False) -> None:
        super().__init__(message)
        self.disk_full = disk_full


def _unavailable(path: Path, exc: sqlite3.Error | OSError) -> StoreUnavailable:
    """The sentence for a database write that failed for a cause outside the service."""
    text = str(exc).lower()
    if "disk is full" in text or getattr(exc, "sqlite_errorcode", None) == 13:
        return StoreUnavailable(
            f"the service's database ({path.name}) cannot be written: the data directory's disk "
            "is full; free some space and try again",
            disk_full=True,
        )
    if "readonly" in text or "read-only" in text:
        return StoreUnavailable(
            f"the service's database ({path.name}) cannot be written: the data directory is "
            "read-only; make it writable again and try again"
        )
    if "locked" in text or "busy" in text:
        return StoreUnavailable(
            f"the service's database ({path.name}) is locked by another program; close it "
            "(or end its transaction) and try again"
        )
    return StoreUnavailable(
        f"the service's database ({path.name}) cannot be written ({exc}); check the data directory's disk and try again"
    )


def _is_outside_cause(exc: BaseException) -> bool:
    """Whether a failed write is the environment's doing (full, read-only, locked, I/O), not a bug of ours."""
    if isinstance(exc, OSError):
        return exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EIO)
    return isinstance(exc, sqlite3.OperationalError) and not str(exc).startswith(("no such", "near "))


def utc_now() -> str:
    """Current UTC time, ISO 8601 with seconds."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


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
        self._kept: dict[tuple[str, str], dict[str, Any]] = {}  # updates not yet written: (table, id) -> columns
        self._kept_log: list[tuple[str, list[str], str]] = []  # log lines not yet written: (job, lines, time)
        self._kept_lock = threading.Lock()
        self._retrying = False
        self.write_problem: str | None = None  # why the last write failed, while updates wait in memory
        self.migrate()

    def _conn(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is not None and getattr(self._local, "identity", None) != self._identity():
            with contextlib.suppress(sqlite3.Error):
                conn.close()  # the file is another one now (its filesystem was checked and mounted again): reopen
            conn = None
        if conn is None:
            conn = sqlite3.connect(self.path, timeout=10.0, isolation_level=None, check_same_thread=False)
            conn.row_factory = sqlite3.Row
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
            conn.execute("PRAGMA foreign_keys=ON")
            self._local.conn = conn
            self._local.identity = self._identity()
        return conn

    def _identity(self) -> tuple[int, int] | None:
        """The database file's device and inode (None while it cannot be seen)."""
        try:
            st = os.stat(self.path)
        except OSError:
            return None
        return st.st_dev, st.st_ino

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
                raise StoreError(
                    f"{self.path}: schema version {current} is newer than this software ({SCHEMA_VERSION})"
                )
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
        try:
            with self._write_lock:
                return self._conn().execute(sql, args).rowcount
        except (sqlite3.Error, OSError) as exc:
            if _is_outside_cause(exc):
                raise _unavailable(self.path, exc) from None
            raise

    # ---------------------------------------------------------------- scans
    def add_scan(
        self, scan_id: str, *, name: str, orbit: str, request: dict[str, Any], file: str, owner: str, frames_total: int
    ) -> None:
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
        self._write(
            "DELETE FROM scans WHERE id = ? AND NOT EXISTS (SELECT 1 FROM jobs WHERE scan_id = ?)", (scan_id, scan_id)
        )

    def get_scan(self, scan_id: str) -> dict[str, Any] | None:
        """One scan, or None."""
        return self._overlaid(
            "scans", _row(self._conn().execute("SELECT * FROM scans WHERE id = ?", (scan_id,)).fetchone())
        )

    def list_scans(self, *, state: str | None = None, limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        """Scans, newest first."""
        sql, args = "SELECT * FROM scans", []
        if state is not None:
            sql, args = sql + " WHERE state = ?", [state]
        rows = self._conn().execute(sql + " ORDER BY rowid DESC LIMIT ? OFFSET ?", (*args, limit, offset))
        out = [self._overlaid("scans", r) for r in map(_row, rows.fetchall()) if r is not None]
        return [r for r in out if r is not None and (state is None or r["state"] == state)]

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
        return self._overlaid(
            "jobs", _row(self._conn().execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone())
        )

    def list_jobs(
        self,
        *,
        kind: str | None = None,
        scan_id: str | None = None,
        state: str | None = None,
        limit: int = 100,
        offset: int = 0,
    ) -> list[dict[str, Any]]:
        """Jobs, newest first, filtered."""
        where, args = [], []
        for column, value in (("kind", kind), ("scan_id", scan_id), ("state", state)):
            if value is not None:
                where.append(f"{column} = ?")
                args.append(value)
        sql = "SELECT * FROM jobs" + (" WHERE " + " AND ".join(where) if where else "")
        rows = self._conn().execute(sql + " ORDER BY rowid DESC LIMIT ? OFFSET ?", (*args, limit, offset))
        out = [self._overlaid("jobs", r) for r in map(_row, rows.fetchall()) if r is not None]
        return [r for r in out if r is not None and (state is None or r["state"] == state)]

    def queued_jobs(self) -> list[dict[str, Any]]:
        """Jobs waiting for a worker, oldest first."""
        rows = self._conn().execute("SELECT * FROM jobs WHERE state = 'queued' ORDER BY rowid").fetchall()
        out = [self._overlaid("jobs", r) for r in map(_row, rows) if r is not None]
        return [r for r in out if r is not None and r["state"] == "queued"]

    def add_log(self, job_id: str, lines: Iterable[str]) -> None:
        """Append lines to a job's log (kept in memory and written later when the database cannot be written now)."""
        entry = (job_id, [line[:2000] for line in lines], utc_now())
        with self._kept_lock:
            waiting = bool(self._kept_log)
            if waiting:  # keep the order: behind the lines already waiting
                self._kept_log.append(entry)
        if waiting:
            return
        try:
            self._insert_log(*entry)
        except (sqlite3.Error, OSError) as exc:
            if not _is_outside_cause(exc):
                raise
            with self._kept_lock:
                self._kept_log.append(entry)
            self._keep_trying(exc)

    def _insert_log(self, job_id: str, lines: list[str], time_utc: str) -> None:
        with self._write_lock:
            conn = self._conn()
            row = conn.execute("SELECT COALESCE(MAX(seq), 0) FROM job_log WHERE job_id = ?", (job_id,)).fetchone()
            start = int(row[0])
            conn.execute("BEGIN IMMEDIATE")
            try:
                conn.executemany(
                    "INSERT INTO job_log (job_id, seq, time_utc, line) VALUES (?, ?, ?, ?)",
                    [(job_id, start + i + 1, time_utc, line) for i, line in enumerate(lines)],
                )
                conn.execute("COMMIT")
            except BaseException:
                conn.execute("ROLLBACK")
                raise

    def job_log(self, job_id: str, *, after: int = 0, limit: int = 1000) -> list[dict[str, Any]]:
        """Log lines of a job after sequence number ``after``."""
        rows = self._conn().execute(
            "SELECT seq, time_utc, line FROM job_log WHERE job_id = ? AND seq > ? ORDER BY seq LIMIT ?",
            (job_id, after, limit),
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
            "SELECT seq, kind, data_json FROM events WHERE topic = ? AND seq > ? ORDER BY seq LIMIT ?",
            (topic, after, limit),
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
            conn.execute(
                f"UPDATE scans SET state = 'interrupted', reason = ?, finished_utc = ? WHERE state IN ({q})",
                (reason, now, *RUNNING_SCAN_STATES),
            )
            conn.execute(
                "UPDATE jobs SET state = 'interrupted', error = 'interrupted', reason = ?, finished_utc = ? "
                "WHERE state = 'running'",
                (reason, now),
            )
        return scans, jobs

    def _update(self, table: str, row_id: str, fields: dict[str, Any]) -> None:
        """Set columns of a row; kept in memory (and retried) when the database cannot be written now."""
        if not fields:
            return
        with self._kept_lock:
            kept = self._kept.get((table, row_id))
            if kept is not None:  # later than what waits: merged into it, written in one go
                kept.update(fields)
                return
        try:
            self._set_columns(table, row_id, fields)
        except StoreUnavailable as exc:
            with self._kept_lock:
                self._kept.setdefault((table, row_id), {}).update(fields)
            self._keep_trying(exc)

    def _overlaid(self, table: str, row: dict[str, Any] | None) -> dict[str, Any] | None:
        """A row as read, with the updates still kept in memory for it applied."""
        if row is None:
            return None
        with self._kept_lock:
            kept = dict(self._kept.get((table, row["id"]), {}))
        row.update(kept)
        return row

    def _keep_trying(self, exc: BaseException) -> None:
        """Start (once) the thread that writes what is kept in memory once the database takes writes again."""
        problem = str(exc) if isinstance(exc, StoreUnavailable) else str(_unavailable(self.path, exc))  # type: ignore[arg-type]
        with self._kept_lock:
            self.write_problem = problem
            if self._retrying:
                return
            self._retrying = True
        log.error("%s; the service keeps the updates in memory and writes them once it can", problem)
        threading.Thread(target=self._write_kept, name="orbitct-db-retry", daemon=True).start()

    def _write_kept(self) -> None:
        while True:
            time.sleep(RETRY_S)
            with self._kept_lock:
                rows = [(key, dict(fields)) for key, fields in self._kept.items()]  # copies: later updates merge
                logs = list(self._kept_log)
            try:
                for (table, row_id), fields in rows:
                    self._set_columns(table, row_id, fields)
                    with self._kept_lock:
                        if self._kept.get((table, row_id)) == fields:
                            del self._kept[(table, row_id)]
                for entry in logs:
                    self._insert_log(*entry)
                    with self._kept_lock:
                        self._kept_log.remove(entry)
            except (StoreUnavailable, sqlite3.Error, OSError) as exc:
                with self._kept_lock:
                    self.write_problem = (
                        str(exc) if isinstance(exc, StoreUnavailable) else str(_unavailable(self.path, exc))
                    )
                continue
            with self._kept_lock:
                if self._kept or self._kept_log:
                    continue
                self._retrying = False
                self.write_problem = None
            log.warning("the service's database takes writes again; the updates kept in memory are written")
            return

    def pending_writes(self) -> int:
        """How many rows and log entries wait in memory to be written."""
        with self._kept_lock:
            return len(self._kept) + len(self._kept_log)

    def _set_columns(self, table: str, row_id: str, fields: dict[str, Any]) -> None:
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
