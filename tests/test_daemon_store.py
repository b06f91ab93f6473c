"""The daemon's SQLite job store: WAL, JSON fields, restart recovery, thread safety."""

from __future__ import annotations

import sqlite3
import threading

import pytest

from capture.daemon.jobs import devices_overlap
from capture.daemon.records import ACTIVE_STATES, ScanRecord
from capture.daemon.store import JobStore


def record(scan_id: str, state: str = "running", created: float = 1.0) -> ScanRecord:
    return ScanRecord(id=scan_id, state=state, devices=["grbl:///dev/ttyUSB0"],
                      request={"plan": {"angles": [0.0, 90.0]}, "camera_url": "oak://"},
                      out_dir=f"scans/{scan_id}", created=created, updated=created)


@pytest.fixture
def store(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite3")
    yield store
    store.close()


def test_the_store_uses_wal_and_round_trips_records(store):
    assert store.journal_mode() == "wal"
    store.insert(record("a" * 16))
    store.update("a" * 16, progress={"views_done": 1, "views_total": 2, "fraction": 0.5},
                 mesh_version=3, mesh_params={"lam": 2.0, "depth": 2, "file": "mesh.ply"})
    got = store.get("a" * 16)
    assert got.request == {"plan": {"angles": [0.0, 90.0]}, "camera_url": "oak://"}
    assert got.devices == ["grbl:///dev/ttyUSB0"]
    assert got.progress["fraction"] == 0.5 and got.mesh_version == 3
    assert got.mesh_params["file"] == "mesh.ply"
    assert got.updated > got.created
    public = got.to_public()
    assert "out_dir" not in public and public["camera_url"] == "oak://"
    assert store.get("b" * 16) is None


def test_restart_lists_every_scan_left_active_as_interrupted(tmp_path):
    path = tmp_path / "jobs.sqlite3"
    first = JobStore(path)
    for i, state in enumerate((*ACTIVE_STATES, "processing", "done", "failed", "interrupted")):
        first.insert(record(f"{i:016x}", state, created=float(i)))
    # the process dies without closing: a second process opens the same file
    second = JobStore(path)
    recovered = second.recover()
    assert recovered == [f"{i:016x}" for i in range(len(ACTIVE_STATES) + 1)]
    states = {r.id: r.state for r in second.list()}
    assert set(states.values()) == {"interrupted", "done", "failed"}
    n = len(ACTIVE_STATES) + 1
    assert states[f"{n:016x}"] == "done" and states[f"{n + 1:016x}"] == "failed"
    assert "daemon stopped" in second.get(f"{0:016x}").reason
    assert second.recover() == []  # nothing left to recover
    first.close()
    second.close()


def test_list_is_newest_first_with_paging_and_delete(store):
    for i in range(5):
        store.insert(record(f"{i:016x}", "done", created=float(i)))
    assert [r.id for r in store.list(2)] == [f"{4:016x}", f"{3:016x}"]
    assert [r.id for r in store.list(2, offset=4)] == [f"{0:016x}"]
    assert store.delete(f"{4:016x}") and not store.delete(f"{4:016x}")
    assert len(store.list()) == 4


def test_bad_updates_are_refused(store):
    store.insert(record("c" * 16))
    with pytest.raises(ValueError, match="colour"):
        store.update("c" * 16, colour="red")
    with pytest.raises(ValueError, match="unknown scan state 'exploded'"):
        store.update("c" * 16, state="exploded")
    with pytest.raises(sqlite3.IntegrityError):
        store.insert(record("c" * 16))


def test_a_newer_schema_is_refused(tmp_path):
    path = tmp_path / "jobs.sqlite3"
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA user_version=99")
    with pytest.raises(RuntimeError, match="newer than this daemon"):
        JobStore(path)


def test_threads_update_one_store_safely(store):
    ids = [f"{i:016x}" for i in range(8)]
    for scan_id in ids:
        store.insert(record(scan_id))

    def work(scan_id):
        for n in range(50):
            store.update(scan_id, progress={"views_done": n + 1})

    threads = [threading.Thread(target=work, args=(scan_id,)) for scan_id in ids]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert all(store.get(scan_id).progress == {"views_done": 50} for scan_id in ids)


@pytest.mark.parametrize("a, b, overlap", [
    ("oak://", "oak://", True),
    ("oak://", "oak://14442C10D13EABCE00", True),  # the first OAK may be that one
    ("oak://14442C10D13EABCE00", "oak://", True),
    ("oak://14442C10D13EABCE00", "oak://192.168.1.44", False),
    ("grbl:///dev/ttyUSB0", "grbl:///dev/ttyUSB1", False),
    ("grbl:///dev/ttyUSB0", "grbl:///dev/ttyUSB0", True),
    ("sim://camera?station=a", "sim://camera?station=b", False),
    ("oak://", "grbl:///dev/ttyUSB0", False),
])
def test_device_keys_that_may_name_one_device(a, b, overlap):
    assert devices_overlap(a, b) is overlap


@pytest.mark.parametrize("a, b", [
    ("grbl://x?port=/dev/ttyUSB0", "grbl:///dev/ttyUSB0"),  # port= is what the driver opens
    ("socket://127.0.0.1:4000", "socket://localhost:4000"),
    ("grbl://?port=socket://localhost:4000", "socket://127.0.0.1:4000?timeout=2"),
    ("grbl://COM3", "grbl://?port=com3"),
])
def test_two_urls_of_one_turntable_hold_one_device(a, b):
    from capture.daemon.schemas import device_keys

    (key_a,), (key_b,) = device_keys(None, a), device_keys(None, b)
    assert devices_overlap(key_a, key_b), (key_a, key_b)


def test_a_serial_port_is_held_by_its_real_path_and_ports_stay_apart(tmp_path):
    from capture.daemon.schemas import device_keys

    port = tmp_path / "ttyACM0"
    port.touch()
    (tmp_path / "by-id").symlink_to(port)
    assert device_keys(None, f"grbl://{tmp_path}/by-id") == device_keys(None, f"grbl://{port}")
    keys = [device_keys(None, url)[0] for url in ("grbl:///dev/ttyUSB0", "grbl:///dev/ttyUSB1",
                                                   "socket://127.0.0.1:4000",
                                                   "socket://127.0.0.1:4001")]
    assert not any(devices_overlap(a, b) for i, a in enumerate(keys) for b in keys[i + 1:])
