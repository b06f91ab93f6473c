"""Shared helpers of the daemon tests (a helper module for the test_daemon_* modules; no tests).

Scans run on the real runner and simulated station: a small camera image and an instant
turntable make a capture-only scan take a fraction of a second; ``settle_s`` slows a scan down
when a test needs it mid-way.
"""

from __future__ import annotations

import socket
import threading
import time
import uuid

import uvicorn


def station_urls(width: int = 160, height: int = 100, instant: bool = True, **camera) -> dict:
    """Device URLs of a fresh simulated station (its own name, so scans never share it)."""
    name = f"t{uuid.uuid4().hex[:8]}"
    options = "".join(f"&{k}={v}" for k, v in camera.items())
    return {
        "camera_url": f"sim://camera?station={name}&width={width}&height={height}{options}",
        "turntable_url": f"sim://turntable?station={name}&instant={int(instant)}",
    }


def capture_plan(views: int = 4, settle_s: float = 0.0, **fields) -> dict:
    """A capture-only plan (no reconstruction) of ``views`` equal steps."""
    return {"angles": [360.0 * i / views for i in range(views)], "frames_per_view": 1,
            "settle_s": settle_s, "reconstruction": None, **fields}


#: the smallest reconstruction that still makes a closed mesh of the simulated vase
#: (use a camera of at least 240 × 150 pixels: `MESH_CAMERA`)
SMALL_RECONSTRUCTION = {"max_layers": 1, "max_neurons": 8, "max_epochs": 5, "final_epochs": 20,
                        "n_sectors": 3, "overlap_deg": 20.0, "update_every": 0,
                        "min_patch_points": 100}
MESH_CAMERA = {"width": 240, "height": 150}


def mesh_plan(views: int = 6, **fields) -> dict:
    return {**capture_plan(views, **fields), "reconstruction": dict(SMALL_RECONSTRUCTION)}


def wait_until(predicate, timeout: float = 30.0, interval: float = 0.02, what="condition"):
    """Poll ``predicate`` until it returns something truthy (returned); fail after ``timeout``,
    saying ``what`` was awaited (a callable: asked then, for what was seen instead)."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            said = what() if callable(what) else what
            raise AssertionError(f"timed out after {timeout:g} s waiting for {said}")
        time.sleep(interval)


def wait_for_state(client, scan_id: str, *states: str, timeout: float = 30.0,
                   headers=None) -> dict:
    """The scan's JSON once its state is one of ``states``."""
    def check():
        scan = client.get(f"/api/v1/scans/{scan_id}", headers=headers).json()
        return scan if scan["state"] in states else None

    return wait_until(check, timeout, what=f"scan {scan_id} to be {'/'.join(states)}")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class LiveServer:
    """A real uvicorn server on loopback running ``app`` in a thread (for streaming clients)."""

    def __init__(self, app, host: str = "127.0.0.1"):
        self.host = host
        self.server = uvicorn.Server(uvicorn.Config(
            app, host=host, port=0, log_level="warning", lifespan="on",
            timeout_graceful_shutdown=2))
        self.thread: threading.Thread | None = None
        self.port = 0

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def __enter__(self) -> LiveServer:
        sock = socket.socket()
        sock.bind((self.host, 0))
        self.port = sock.getsockname()[1]
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [sock]},
                                       name="test-uvicorn")
        self.thread.start()
        wait_until(lambda: self.server.started or not self.thread.is_alive(), 20,
                   what="uvicorn to start")
        if not self.server.started:
            raise RuntimeError("uvicorn did not start")
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(20)


def one_line_detail(response) -> str:
    detail = response.json()["detail"]
    assert isinstance(detail, str) and "\n" not in detail
    return detail


class GatedRunner:
    """A runner whose start blocks until the test opens ``gate`` (a device that has not
    answered yet); then it runs until cancelled."""

    def __init__(self, gate: threading.Event):
        self.gate, self.state, self.reason = gate, "idle", ""
        self.started, self._ended = threading.Event(), threading.Event()
        self.documents = []

    def subscribe(self, callback):
        return lambda: None

    def start(self):
        self.started.set()
        self.gate.wait(30)
        self.state = "running"
        return self

    def pause(self):
        raise RuntimeError("not in this test")

    resume = pause

    def cancel(self):
        self.state, self.reason = "interrupted", "cancelled by the user"
        self._ended.set()

    def wait(self, timeout=None):
        self._ended.wait(timeout)
        return self.state
