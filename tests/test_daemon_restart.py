"""`scanstation serve` as a real process: SIGKILL mid-scan, restart, the scan is interrupted with
its recording intact, and resume finishes it (with a mesh); SIGTERM stops it cleanly."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys

import httpx
import pytest
import trimesh
from daemon_helpers import MESH_CAMERA, free_port, mesh_plan, station_urls, wait_until

from capture.recording import read_recording

VIEWS = 8


class Daemon:
    """``python -m capture.cli serve`` on a free loopback port, its output in a file."""

    def __init__(self, state_dir, log_path):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = log_path
        with open(log_path, "wb") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "capture.cli", "serve", "--port", str(self.port),
                 "--state-dir", str(state_dir)], stdout=log, stderr=subprocess.STDOUT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.http = httpx.Client(base_url=self.url, timeout=30)
        wait_until(self._healthy, 60, interval=0.1, what=f"the daemon on port {self.port}")

    def _healthy(self) -> bool:
        if self.process.poll() is not None:
            raise AssertionError(f"the daemon exited: {self.output()}")
        try:
            return self.http.get("/healthz").status_code == 200
        except httpx.TransportError:
            return False

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def scan(self, scan_id: str) -> dict:
        return self.http.get(f"/api/v1/scans/{scan_id}").json()

    def stop(self, sig=signal.SIGTERM) -> int:
        self.http.close()
        self.process.send_signal(sig)
        return self.process.wait(30)


@pytest.fixture
def daemons():
    started = []
    yield started
    for daemon in started:
        if daemon.process.poll() is None:
            daemon.process.kill()
            daemon.process.wait(30)


def test_sigkill_mid_scan_then_restart_resume_finishes_it(tmp_path, daemons):
    state_dir = tmp_path / "state"
    first = Daemon(state_dir, tmp_path / "first.log")
    daemons.append(first)
    assert "API token (shown once" in first.output()
    body = {"plan": mesh_plan(VIEWS, settle_s=0.25), **station_urls(**MESH_CAMERA)}
    created = first.http.post("/api/v1/scans", json=body)
    assert created.status_code == 201, created.text
    scan_id = created.json()["id"]
    seen = wait_until(lambda: (first.scan(scan_id)["progress"]["views_done"] >= 3
                               and first.scan(scan_id)["progress"]["views_done"]), 60,
                      what="three views")
    first.stop(signal.SIGKILL)
    assert first.process.returncode == -signal.SIGKILL

    folder = state_dir / "scans" / scan_id
    # the orphaned scan child stops by itself and says why (not "cancelled by the user")
    report = wait_until(lambda: (folder / "scan.json").is_file() and json.loads(
        (folder / "scan.json").read_text()), 60, what="the orphaned child's report")
    assert report["state"] == "interrupted"
    assert "the daemon" in report["reason"] and "user" not in report["reason"]
    recording = read_recording(folder)  # no footer: read with the non-seeking reader
    recorded = [view.index for view in recording.views]
    assert recorded == list(range(len(recorded))) and seen <= len(recorded) < VIEWS

    second = Daemon(state_dir, tmp_path / "second.log")
    daemons.append(second)
    assert "API token" not in second.output()  # printed once, at the first start only
    after = second.scan(scan_id)
    assert after["state"] == "interrupted"
    assert "daemon stopped" in after["reason"]
    assert after["progress"]["views_done"] <= len(recorded)
    assert second.http.post(f"/api/v1/scans/{scan_id}/resume").status_code == 202
    done = wait_until(lambda: (s := second.scan(scan_id))["state"] in ("done", "failed") and s,
                      180, interval=0.2, what="the resumed scan to end")
    assert done["state"] == "done", done["reason"]
    assert done["progress"]["views_done"] == VIEWS
    views = read_recording(folder).views
    assert sorted(view.index for view in views) == list(range(VIEWS))
    assert done["files"]["recording_segments"] == 2
    mesh = second.http.get(f"/api/v1/scans/{scan_id}/mesh", params={"format": "ply"})
    assert len(trimesh.load(io.BytesIO(mesh.content), file_type="ply").faces) > 500

    # graceful stop: the lifespan ran (uvicorn re-raises SIGTERM after it; systemd counts
    # an exit by SIGTERM as clean)
    assert second.stop(signal.SIGTERM) in (0, -signal.SIGTERM)
    assert "Application shutdown complete" in second.output()


@pytest.mark.parametrize("delay", [0.3, 0.8])
def test_a_daemon_stopped_during_its_first_device_discovery_exits_cleanly(tmp_path, delay):
    # the interpreter aborted (SIGABRT, 134) when it exited with the discovery thread inside
    # depthai's: the daemon's stop waits for it
    script = (
        "import sys, time\n"
        "from fastapi.testclient import TestClient\n"
        "from capture.daemon.app import create_app\n"
        "with TestClient(create_app(sys.argv[1])) as client:\n"
        "    assert client.get('/healthz').status_code == 200\n"
        "    time.sleep(float(sys.argv[2]))\n")
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path / "state"), str(delay)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
