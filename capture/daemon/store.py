"""The daemon's job store: one SQLite database (WAL) in the state dir, one row per scan.

The store outlives the process: `JobStore.recover` (called at start) lists every scan that was
still active when the previous daemon died as ``interrupted`` — its recording stays on disk and
the scan can be resumed or re-processed. Writes are serialised by a lock so that runner threads
and request threads can share one connection. One process owns the file (the daemon), so rows
are also kept in memory: `get` answers status polls without touching the disk.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import logging
import os
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

from .errors import DaemonError
from .records import ACTIVE_STATES, STATES, ScanRecord

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
_SIDE_FILES = ("-wal", "-shm")


class StoreError(DaemonError, RuntimeError):
    """A job store the daemon cannot use or repair (one line naming the file and the fix)."""


class _Damaged(sqlite3.DatabaseError):
    """The store's integrity check failed."""


def _is_damage(exc: Exception) -> bool:
    """Whether opening or reading failed because the file's content is damaged (not because
    it cannot be opened, is locked or read-only)."""
    if isinstance(exc, (_Damaged, ValueError)):
        return True
    name = getattr(exc, "sqlite_errorname", "")  # Python >= 3.11
    text = str(exc).lower()
    return name in ("SQLITE_CORRUPT", "SQLITE_NOTADB") or "malformed" in text or \
        "not a database" in text

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


class JobStore:
    """Scans in ``state_dir/daemon.sqlite3``; every method is thread-safe.

    Opening checks the file. A damaged store (truncated, garbage, rows that do not parse) is
    moved aside as ``daemon.sqlite3.damaged-<time>`` and rebuilt; with ``scans_dir``, every scan
    folder without a row (a rebuilt or an emptied store) gets one back from its ``scan.json``
    and recording (`capture.daemon.rebuild`), so no scan is silently forgotten. What cannot be
    repaired raises `StoreError`.
    """

    def __init__(self, path: str | Path, scans_dir: str | Path | None = None):
        self.path = Path(path)
        self._lock = threading.Lock()
        self._cache: dict[str, ScanRecord] = {}
        try:
            self._open()
            bad = self._load_all()
        except StoreError:
            raise
        except (sqlite3.DatabaseError, ValueError) as exc:
            if not _is_damage(exc):  # e.g. not ours to read: moving it aside would not help
                raise StoreError(f"{self.path}: cannot open the job store ({exc}): check the "
                                 "file's owner and permissions") from exc
            self._set_aside(exc)
            self._open()
            bad = []
        if bad:
            self._drop_bad_rows(bad)
        if scans_dir is not None:
            self.adopt(Path(scans_dir))

    def _open(self) -> None:
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.row_factory = sqlite3.Row
        with contextlib.suppress(OSError):
            os.chmod(self.path, 0o600)  # its -wal and -shm files take the same mode
        with self._lock:
            self._db.execute("PRAGMA busy_timeout=5000")
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            if version not in (0, SCHEMA_VERSION):
                self._db.close()
                raise StoreError(f"{self.path}: job store schema {version} is newer than this "
                                 f"daemon's ({SCHEMA_VERSION}): upgrade ScanStation, or move the "
                                 "file away to rebuild the store from the scan folders")
            check = self._db.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                raise _Damaged(f"integrity check: {check}")
            self._db.executescript(SCHEMA)
            self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")

    def _load_all(self) -> list[str]:
        """Read every row into the cache; the ids of rows that do not parse."""
        bad = []
        with self._lock:
            rows = self._db.execute("SELECT * FROM scans").fetchall()
            for row in rows:
                try:
                    record = self._from_row(row)
                except (ValueError, TypeError, KeyError) as exc:
                    log.warning("%s: scan %r has a damaged row (%s)", self.path, row["id"], exc)
                    bad.append(row["id"])
                    continue
                self._cache[record.id] = record
        return bad

    def _set_aside(self, cause: Exception) -> None:
        """Move the damaged file (and its WAL) aside; the caller opens a new one."""
        with contextlib.suppress(Exception):
            self._db.close()
        aside = self.path.with_name(f"{self.path.name}.damaged-{time.strftime('%Y%m%dT%H%M%S')}")
        try:
            for suffix in ("", *_SIDE_FILES):
                source = Path(f"{self.path}{suffix}")
                if source.exists():
                    os.replace(source, f"{aside}{suffix}")
        except OSError as exc:
            raise StoreError(f"{self.path} is damaged ({cause}) and could not be moved aside "
                             f"({exc.strerror or exc}): move it away by hand; the daemon then "
                             "rebuilds it from the scan folders") from exc
        log.warning("job store %s was damaged (%s): kept aside as %s; rebuilding it from the "
                    "scan folders", self.path, str(cause).splitlines()[0], aside.name)

    def _drop_bad_rows(self, ids: list[str]) -> None:
        """Keep a copy of the store aside, then delete the rows that do not parse (their scans
        come back from their folders)."""
        aside = self.path.with_name(f"{self.path.name}.damaged-{time.strftime('%Y%m%dT%H%M%S')}")
        with self._lock:
            self._db.execute("VACUUM INTO ?", (str(aside),))
            self._db.executemany("DELETE FROM scans WHERE id=?", [(i,) for i in ids])
        with contextlib.suppress(OSError):
            os.chmod(aside, 0o600)
        log.warning("job store %s: %d damaged row(s) kept aside in %s and rebuilt from the scan "
                    "folders", self.path, len(ids), aside.name)

    def adopt(self, scans_dir: Path) -> list[str]:
        """Give every scan folder without a row one, rebuilt from the folder; their ids."""
        from .rebuild import SCAN_FOLDER, record_from_folder

        if not scans_dir.is_dir():
            return []
        with self._lock:
            known = {row[0] for row in self._db.execute("SELECT id FROM scans")}
        adopted = []
        for folder in sorted(scans_dir.iterdir()):
            if folder.name in known or not SCAN_FOLDER.match(folder.name) or \
                    not folder.is_dir():
                continue
            record = record_from_folder(folder, f"{scans_dir.name}/{folder.name}")
            self.insert(record)
            adopted.append(record.id)
        if adopted:
            log.warning("job store %s: %d scan(s) rebuilt from their folders: %s", self.path,
                        len(adopted), ", ".join(adopted))
        return adopted

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
        """The record of a row; ValueError when a field does not hold what it should."""
        data = dict(row)
        for key in _JSON_FIELDS:
            data[key] = json.loads(data[key])
        kinds = {"devices": list, "request": dict, "progress": dict, "mesh_params": dict}
        wrong = [key for key, kind in kinds.items() if not isinstance(data[key], kind)]
        if wrong or data["state"] not in STATES:
            raise ValueError(f"field(s) {', '.join(wrong) or 'state'} hold the wrong kind")
        return ScanRecord(**data)
