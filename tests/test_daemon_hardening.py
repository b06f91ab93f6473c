"""The daemon's smaller hardening findings (issue 14, item 8): JSON and same-origin on
state-changing routes, a strict Host guard, a body read timeout, a private state dir, the
systemd unit's sandbox, and a killed daemon's scan process that is not run twice."""

from __future__ import annotations

import os
import socket
import stat

import pytest
from daemon_helpers import LiveServer, capture_plan, station_urls, wait_for_state
from daemon_helpers import one_line_detail as _detail
from fastapi.testclient import TestClient

from capture.daemon.app import create_app


def test_state_changing_routes_take_only_json_from_the_same_origin(client):
    scan = client.post("/api/v1/scans", json={"plan": capture_plan(40, settle_s=0.2),
                                              **station_urls()}).json()
    cancel = f"/api/v1/scans/{scan['id']}/cancel"
    plain = client.post(cancel, content=b"x", headers={"content-type": "text/plain"})
    assert plain.status_code == 415
    form = client.post(cancel, content=b"a=1",
                       headers={"content-type": "application/x-www-form-urlencoded"})
    assert form.status_code == 415
    foreign = client.post(cancel, json={}, headers={"origin": "http://evil.example"})
    assert foreign.status_code == 403
    assert client.delete(f"/api/v1/scans/{scan['id']}",
                         headers={"origin": "http://evil.example"}).status_code == 403
    assert client.get(f"/api/v1/scans/{scan['id']}").json()["state"] in ("starting", "running")
    ok = client.post(cancel, headers={"origin": "http://testserver"})
    assert ok.status_code == 202
    wait_for_state(client, scan["id"], "interrupted")


@pytest.mark.parametrize("host", [
    "127.0.0.1:8765@evil.example", "localhost@evil.example", "127.0.0.1:80:81",
    "127.0.0.1/evil", "127.0.0.1:abc", "evil.example#127.0.0.1", "[::1]x", ""])
def test_the_host_guard_takes_only_a_plain_loopback_host(state_dir, host):
    with TestClient(create_app(state_dir, loopback_hosts_only=True)) as client:
        assert client.get("/healthz", headers={"host": host}).status_code == 421
        assert client.get("/healthz", headers={"host": "127.0.0.1:8765"}).status_code == 200


def test_a_body_that_stops_short_times_out(state_dir):
    with LiveServer(create_app(state_dir, body_timeout_s=0.5)) as server, \
            socket.create_connection((server.host, server.port), timeout=20) as sock:
        sock.sendall(b"POST /api/v1/scans HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                     b"Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{\"pl")
        answer = sock.recv(4096)
    assert answer.startswith(b"HTTP/1.1 408"), answer


def test_the_state_dir_and_its_files_are_private(state_dir):
    with TestClient(create_app(state_dir)) as client:
        scan = client.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                  **station_urls()}).json()
        wait_for_state(client, scan["id"], "done")
    assert stat.S_IMODE(state_dir.stat().st_mode) == 0o700
    for path in state_dir.rglob("*"):
        mode = stat.S_IMODE(path.stat().st_mode)
        assert mode & 0o077 == 0, f"{path.relative_to(state_dir)} is {mode:o}"


def test_an_existing_open_state_dir_is_tightened(state_dir):
    state_dir.mkdir(mode=0o755)
    os.chmod(state_dir, 0o755)
    with TestClient(create_app(state_dir)):
        pass
    assert stat.S_IMODE(state_dir.stat().st_mode) == 0o700


def test_systemd_unit_is_hardened():
    import pathlib
    import shutil
    import subprocess

    unit = pathlib.Path(__file__).parents[1] / "deploy" / "scanstation.service"
    text = unit.read_text()
    for option in ("UMask=0077", "MemoryMax=", "TasksMax=", "RestrictAddressFamilies=",
                   "SystemCallFilter=", "CapabilityBoundingSet=", "PrivateDevices=no",
                   "ProtectKernelTunables=yes", "LockPersonality=yes"):
        assert option in text, option
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze not installed: options checked by name only")
    out = subprocess.run(["systemd-analyze", "security", "--offline=yes", str(unit)],
                         capture_output=True, text=True, timeout=60)
    line = [x for x in out.stdout.splitlines() if "Overall exposure level" in x]
    assert line, out.stdout + out.stderr
    score = float(line[0].split(":")[1].split()[0])
    assert score <= 4.0, line[0]


def test_a_scan_whose_orphaned_process_still_runs_is_not_resumed_twice(client, state_dir):
    import fcntl

    scan = client.post("/api/v1/scans", json={"plan": capture_plan(30, settle_s=0.2),
                                              **station_urls()}).json()
    wait_for_state(client, scan["id"], "running")
    client.post(f"/api/v1/scans/{scan['id']}/cancel")
    wait_for_state(client, scan["id"], "interrupted")
    # a killed daemon's scan process still holds the folder
    with open(state_dir / "scans" / scan["id"] / ".scan.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        busy = client.post(f"/api/v1/scans/{scan['id']}/resume")
        assert busy.status_code == 409 and "still stopping" in _detail(busy)
        assert client.post(f"/api/v1/scans/{scan['id']}/reprocess").status_code == 409
    resumed = client.post(f"/api/v1/scans/{scan['id']}/resume")
    assert resumed.status_code == 202
    wait_for_state(client, scan["id"], "running")
    client.post(f"/api/v1/scans/{scan['id']}/cancel")
    wait_for_state(client, scan["id"], "interrupted")
