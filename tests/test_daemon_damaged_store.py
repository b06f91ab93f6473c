"""A damaged job store (issue 14, item 7): the daemon rebuilds it from the scan folders, keeps
the damaged file aside and forgets no scan; what it cannot repair is one line naming the file
and the fix."""

from __future__ import annotations

import shutil
import sqlite3
import subprocess
import sys

import pytest
from daemon_helpers import capture_plan, station_urls, wait_for_state, wait_until
from fastapi.testclient import TestClient

from capture.daemon.app import DATABASE, create_app
from capture.daemon.store import JobStore, StoreError


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    """A state dir holding a done scan, an interrupted one (cancelled mid-way) and a failed
    one (bad turntable: no folder content but its row)."""
    state_dir = tmp_path_factory.mktemp("daemon") / "state"
    with TestClient(create_app(state_dir)) as client:
        done = client.post("/api/v1/scans", json={"plan": capture_plan(3),
                                                  **station_urls()}).json()
        wait_for_state(client, done["id"], "done")
        slow = client.post("/api/v1/scans", json={"plan": capture_plan(30, settle_s=0.2),
                                                  **station_urls()}).json()
        wait_until(lambda: client.get(f"/api/v1/scans/{slow['id']}").json()["progress"]
                   ["views_done"] >= 2, what="two views")
        client.post(f"/api/v1/scans/{slow['id']}/cancel")
        wait_for_state(client, slow["id"], "interrupted")
        states = {s["id"]: s for s in client.get("/api/v1/scans").json()["scans"]}
    return state_dir, states


@pytest.fixture
def copy(scanned, tmp_path):
    state_dir, states = scanned
    target = tmp_path / "state"
    shutil.copytree(state_dir, target)
    return target, states


def _listed(state_dir) -> dict:
    with TestClient(create_app(state_dir)) as client:
        scans = client.get("/api/v1/scans").json()["scans"]
        for scan in scans:  # every scan answers (no 500 on any of them)
            assert client.get(f"/api/v1/scans/{scan['id']}").status_code == 200
            assert client.get(f"/api/v1/scans/{scan['id']}/report").status_code in (200, 404)
        return {s["id"]: s for s in scans}


def _check_rebuilt(listed: dict, states: dict) -> None:
    assert set(listed) == set(states)  # no scan forgotten
    for scan_id, before in states.items():
        assert listed[scan_id]["state"] == before["state"], scan_id
        assert listed[scan_id]["progress"]["views_done"] == before["progress"]["views_done"]
        assert listed[scan_id]["plan"]["n_views"] == before["plan"]["n_views"]


def _aside(state_dir) -> list:
    return sorted(p.name for p in state_dir.glob(f"{DATABASE}.damaged-*"))


def test_a_zero_length_store_is_rebuilt_from_the_scan_folders(copy):
    state_dir, states = copy
    (state_dir / DATABASE).write_bytes(b"")
    for suffix in ("-wal", "-shm"):
        (state_dir / (DATABASE + suffix)).unlink(missing_ok=True)
    _check_rebuilt(_listed(state_dir), states)


def test_a_truncated_store_is_kept_aside_and_rebuilt(copy):
    state_dir, states = copy
    with TestClient(create_app(state_dir)):
        pass  # a clean stop checkpoints the WAL into the file
    path = state_dir / DATABASE
    data = path.read_bytes()
    assert len(data) > 4096
    path.write_bytes(data[: len(data) // 2 + 100])
    _check_rebuilt(_listed(state_dir), states)
    kept = _aside(state_dir)
    assert kept and (state_dir / kept[0]).read_bytes() == data[: len(data) // 2 + 100]


def test_garbage_in_the_store_is_kept_aside_and_rebuilt(copy):
    state_dir, states = copy
    with TestClient(create_app(state_dir)):
        pass
    path = state_dir / DATABASE
    data = bytearray(path.read_bytes())
    data[100:] = bytes((i * 37 + 11) % 256 for i in range(len(data) - 100))
    path.write_bytes(bytes(data))
    _check_rebuilt(_listed(state_dir), states)
    assert _aside(state_dir)


def test_a_row_with_garbage_fields_does_not_500(copy):
    state_dir, states = copy
    victim = next(iter(states))
    with sqlite3.connect(state_dir / DATABASE) as db:
        db.execute("UPDATE scans SET progress='{not json', request='[' WHERE id=?", (victim,))
        db.execute("UPDATE scans SET state='exploded' WHERE id<>?", (victim,))
    _check_rebuilt(_listed(state_dir), states)


def test_a_missing_row_is_adopted_from_its_folder(copy):
    state_dir, states = copy
    victim = next(iter(states))
    with sqlite3.connect(state_dir / DATABASE) as db:
        db.execute("DELETE FROM scans WHERE id=?", (victim,))
    _check_rebuilt(_listed(state_dir), states)


def test_what_cannot_be_repaired_is_one_line_naming_the_file_and_the_fix(tmp_path):
    path = tmp_path / "state" / DATABASE
    path.parent.mkdir(mode=0o700)
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA user_version=99")
    with pytest.raises(StoreError) as caught:
        JobStore(path)
    message = str(caught.value)
    assert str(path) in message and "\n" not in message and "upgrade" in message
    serve = subprocess.run(
        [sys.executable, "-m", "capture.cli", "serve", "--port", "0", "--state-dir",
         str(path.parent)], capture_output=True, text=True, timeout=60)
    assert serve.returncode != 0
    lines = [line for line in serve.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and str(path) in lines[0] and "Traceback" not in serve.stderr, \
        serve.stderr
