"""The daemon's job store: one SQLite database (WAL) in the state dir, one row per scan.

The store outlives the process: `JobStore.recover` (called at start) lists every scan that was
still active when the previous daemon died as ``interrupted`` — its recording stays on disk and
the scan can be resumed or re-processed. Writes are serialised by a lock so that runner threads
and request threads can share one connection. One process owns the file (the daemon), so rows
are also kept in memory: `get` answers status polls without touching the disk.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

#: runner states in which a scan holds its devices
ACTIVE_STATES = ("idle", "running", "paused", "stopping")
#: states a scan ends in (re-processing a scan runs it again through `processing`)
FINAL_STATES = ("done", "failed", "interrupted")
STATES = (*ACTIVE_STATES, "processing", *FINAL_STATES)

SCHEMA_VERSION = 1
SCHEMA = """
CREATE TABLE IF NOT EXISTS scans (
    id TEXT PRIMARY KEY,
    state TEXT NOT NULL,
    devices TEXT NOT NULL,          -- JSON list of device keys the scan holds while active
    request TEXT NOT NULL,          -- JSON: plan, camera_url, turntable_url, object
    out_dir TEXT NOT NULL,          -- relative to the state dir
    created REAL NOT NULL,          -- unix seconds
    updated REAL NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    progress TEXT NOT NULL DEFAULT '{}',
    mesh_version INTEGER NOT NULL DEFAULT 0,
    mesh_params TEXT NOT NULL DEFAULT '{}'
);
CREATE INDEX IF NOT EXISTS scans_created ON scans (created);
"""
_JSON_FIELDS = ("devices", "request", "progress", "mesh_params")


@dataclasses.dataclass
class ScanRecord:
    """One scan as stored. ``progress``: views_done, views_total, fraction (from the runner's
    documents); ``mesh_version`` counts meshes (engine updates and refines); ``mesh_params``:
    the λ and depth of the current mesh."""

    id: str
    state: str
    devices: list[str]
    request: dict[str, Any]
    out_dir: str
    created: float
    updated: float
    reason: str = ""
    progress: dict[str, Any] = dataclasses.field(default_factory=dict)
    mesh_version: int = 0
    mesh_params: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_public(self) -> dict[str, Any]:
        """The JSON the API answers (no server paths)."""
        data = dataclasses.asdict(self)
        data.pop("out_dir")
        for key in ("camera_url", "turntable_url", "object"):
            data[key] = self.request.get(key)
        data["plan"] = self.request.get("plan")
        data.pop("request")
        return data


class JobStore:
    """Scans in ``state_dir/daemon.sqlite3``; every method is thread-safe."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.row_factory = sqlite3.Row
        self._cache: dict[str, ScanRecord] = {}
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA busy_timeout=5000")
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            if version not in (0, SCHEMA_VERSION):
                raise RuntimeError(f"{self.path}: job store schema {version} is newer than "
                                   f"this daemon's ({SCHEMA_VERSION})")
            self._db.executescript(SCHEMA)
            self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")

    def journal_mode(self) -> str:
        with self._lock:
            return self._db.execute("PRAGMA journal_mode").fetchone()[0]

    def recover(self, reason: str = "the daemon stopped while the scan was active") -> list[str]:
        """Mark every scan left active (or processing) by a previous process ``interrupted``."""
        stale = (*ACTIVE_STATES, "processing")
        marks = ",".join("?" * len(stale))
        with self._lock:
            rows = self._db.execute(
                f"UPDATE scans SET state='interrupted', reason=?, updated=? "
                f"WHERE state IN ({marks}) RETURNING id", (reason, time.time(), *stale)
            ).fetchall()
            self._cache.clear()
        return sorted(row["id"] for row in rows)

    def insert(self, record: ScanRecord) -> None:
        row = self._to_row(record)
        names = ",".join(row)
        marks = ",".join("?" * len(row))
        with self._lock:
            self._db.execute(f"INSERT INTO scans ({names}) VALUES ({marks})", tuple(row.values()))

    def update(self, scan_id: str, **fields) -> None:
        """Change some fields of a scan (``updated`` is set to now)."""
        unknown = set(fields) - {f.name for f in dataclasses.fields(ScanRecord)}
        if unknown or "id" in fields:
            raise ValueError(f"cannot update field(s) {', '.join(sorted(unknown or {'id'}))}")
        if fields.get("state", "running") not in STATES:
            raise ValueError(f"unknown scan state {fields['state']!r}")
        fields["updated"] = time.time()
        values = {k: json.dumps(v) if k in _JSON_FIELDS else v for k, v in fields.items()}
        assignments = ",".join(f"{name}=?" for name in values)
        with self._lock:
            self._db.execute(f"UPDATE scans SET {assignments} WHERE id=?",
                             (*values.values(), scan_id))
            self._cache.pop(scan_id, None)

    def get(self, scan_id: str) -> ScanRecord | None:
        """The scan (a copy: changing it changes nothing stored), or None."""
        with self._lock:
            record = self._cache.get(scan_id)
            if record is None:
                row = self._db.execute("SELECT * FROM scans WHERE id=?", (scan_id,)).fetchone()
                if row is None:
                    return None
                record = self._cache[scan_id] = self._from_row(row)
            return copy.deepcopy(record)

    def list(self, limit: int = 100, offset: int = 0) -> list[ScanRecord]:
        """Newest first."""
        with self._lock:
            rows = self._db.execute(
                "SELECT * FROM scans ORDER BY created DESC, id LIMIT ? OFFSET ?", (limit, offset)
            ).fetchall()
        return [self._from_row(row) for row in rows]

    def delete(self, scan_id: str) -> bool:
        with self._lock:
            cursor = self._db.execute("DELETE FROM scans WHERE id=?", (scan_id,))
            self._cache.pop(scan_id, None)
        return cursor.rowcount > 0

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @staticmethod
    def _to_row(record: ScanRecord) -> dict[str, Any]:
        row = dataclasses.asdict(record)
        for key in _JSON_FIELDS:
            row[key] = json.dumps(row[key])
        return row

    @staticmethod
    def _from_row(row: sqlite3.Row) -> ScanRecord:
        data = dict(row)
        for key in _JSON_FIELDS:
            data[key] = json.loads(data[key])
        return ScanRecord(**data)
