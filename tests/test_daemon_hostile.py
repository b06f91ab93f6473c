"""The daemon under hostile and careless use (issue 14, items 1-6): nothing blocks, nothing
leaks, nothing answers 500. Each test reproduces one finding; scans run on the real runner
(child processes) and simulated stations unless a gated fake runner makes a race deterministic.
The smaller findings (item 8) are in test_daemon_hardening.py, the damaged job store (item 7)
in test_daemon_damaged_store.py."""

from __future__ import annotations

import socket
import threading

import pytest
from daemon_helpers import (
    GatedRunner,
    LiveServer,
    capture_plan,
    station_urls,
    wait_for_state,
    wait_until,
)
from daemon_helpers import one_line_detail as _detail
from fastapi.testclient import TestClient

from capture.daemon.app import create_app


# -- 1. the event loop never waits on a device or a child -------------------------------------
def test_post_answers_starting_while_the_device_has_not_answered_and_the_api_stays_live(
        state_dir):
    gate, runners = threading.Event(), []

    def factory(plan, **kwargs):
        runners.append(GatedRunner(gate))
        return runners[-1]

    with TestClient(create_app(state_dir, runner_factory=factory)) as client:
        answer: list = []
        poster = threading.Thread(target=lambda: answer.append(
            client.post("/api/v1/scans", json={"plan": capture_plan(2)})))
        poster.start()
        poster.join(10)  # a deadlock guard, not a timing check: the gate is still closed
        assert answer, "POST waited for the device"
        assert answer[0].status_code == 201, answer[0].text
        scan = answer[0].json()
        assert scan["state"] == "starting"
        # the runner is built on the scan's own thread, after the POST has answered
        wait_until(lambda: runners, timeout=10, what="the runner to be built")
        assert runners[0].started.wait(10)
        assert client.get("/healthz").json()["status"] == "ok"
        assert client.get(f"/api/v1/scans/{scan['id']}").json()["state"] == "starting"
        assert client.get("/api/v1/scans").status_code == 200
        gate.set()
        wait_for_state(client, scan["id"], "running")
        client.post(f"/api/v1/scans/{scan['id']}/cancel")
        assert wait_for_state(client, scan["id"], "interrupted")["state"] == "interrupted"


def test_a_turntable_that_never_answers_fails_its_scan_in_the_child_not_the_request(client):
    with socket.socket() as listener:  # accepts (backlog) and never says a word
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        body = {"plan": capture_plan(2),
                "turntable_url": f"socket://127.0.0.1:{port}?timeout=4"}
        created = client.post("/api/v1/scans", json=body)
        assert created.status_code == 201, created.text
        assert created.json()["state"] == "starting"  # the device cannot have answered
        assert client.get("/healthz").status_code == 200
        ended = wait_for_state(client, created.json()["id"], "failed", "done", timeout=60)
    assert ended["state"] == "failed"
    assert "no GRBL banner" in ended["reason"]


@pytest.mark.parametrize("url", [
    "socket://127.0.0.1:9?timeout=1000",
    "socket://127.0.0.1:9?timeout=1e308",
    "grbl:///dev/ttyUSB0?timeout=31",
    "grbl:///dev/ttyUSB0?link_timeout=500",
    "grbl://?port=socket://127.0.0.1:9&timeout=99",
])
def test_device_timeouts_over_the_maximum_are_refused(client, url):
    response = client.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                  "turntable_url": url})
    assert response.status_code == 422
    assert "timeout" in _detail(response)


# -- 2. device addresses and object files come from the operator ------------------------------
@pytest.mark.parametrize("url", [
    "socket://10.0.0.5:23",
    "socket://example.com:23",
    "rfc2217://192.168.1.20:2217",
    "grbl://?port=socket://10.0.0.5:23",
    "grbl:///etc/passwd",
    "grbl://?port=/home/user/fifo",
])
def test_remote_or_non_serial_turntables_need_the_operators_allowlist(client, url):
    response = client.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                  "turntable_url": url})
    assert response.status_code == 422
    assert "--allow-device" in _detail(response)
    assert client.get("/api/v1/scans").json()["scans"] == []


def test_the_allowlist_admits_what_the_operator_named():
    from capture.daemon.policy import DevicePolicy

    policy = DevicePolicy(allow=["socket://10.0.0.5:23", "grbl:///srv/ports/table"])
    policy.check_url("turntable", "socket://10.0.0.5:23?timeout=2")
    policy.check_url("turntable", "grbl://?port=socket://10.0.0.5:23")
    policy.check_url("turntable", "grbl:///srv/ports/table")
    policy.check_url("turntable", "socket://127.0.0.1:4000")  # loopback: always
    policy.check_url("turntable", "grbl:///dev/ttyUSB0")  # serial: always
    policy.check_url("camera", "oak://")
    for url in ("socket://10.0.0.5:24", "socket://10.0.0.6:23", "grbl:///srv/ports/other",
                "grbl:///dev/../etc/passwd"):
        with pytest.raises(ValueError, match="--allow-device"):
            policy.check_url("turntable", url)


@pytest.mark.parametrize("url, said", [
    ("sim://camera?object=/etc/hostname", "request's `object` field"),
    ("sim://camera?object=vase", "request's `object` field"),
    ("sim://camera?width=40000&height=40000", "maximum of 4096 pixels"),
    ("sim://camera?height=100000", "maximum of 4096 pixels"),
])
def test_a_simulated_camera_url_may_not_name_a_file_or_a_huge_image(client, url, said):
    response = client.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                  "camera_url": url, "object": "vase"})
    assert response.status_code == 422, response.text
    assert said in _detail(response)
    assert client.get("/api/v1/scans").json()["scans"] == []


def test_object_files_only_from_the_operators_folder_and_errors_leak_no_host_paths(
        state_dir, tmp_path):
    folder = tmp_path / "objects"
    folder.mkdir()
    outside = tmp_path / "outside.stl"
    outside.write_text("solid x\nendsolid x\n")
    (folder / "link.stl").symlink_to(outside)
    with TestClient(create_app(state_dir)) as client:  # no folder: built-in names only
        refused = client.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                     "object": str(outside)})
        assert refused.status_code == 422 and "--object-dir" in _detail(refused)
    with TestClient(create_app(state_dir, object_dir=folder)) as client:
        details = set()
        for name in (str(outside), "/etc/passwd", "/no/such/file.stl", "../outside.stl",
                     "link.stl", "/etc", str(folder / ".." / "outside.stl")):
            response = client.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                           "object": name})
            assert response.status_code == 422, name
            details.add(_detail(response).replace(repr(name), "NAME"))
        assert len(details) == 1, details  # the same answer whether the path exists or not
        assert str(tmp_path) not in details.pop()
        missing = client.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                     "object": "nope.stl"})
        assert missing.status_code == 422 and str(folder) not in _detail(missing)


# -- 3. a large object file is checked cheaply, and loaded only in the child ------------------
def test_object_files_are_checked_by_size_and_type_without_parsing(state_dir, tmp_path,
                                                                   monkeypatch):
    import sim.camera
    import sim.objects

    def no_parsing_here(*args, **kwargs):
        raise AssertionError("the daemon parsed a mesh file")

    monkeypatch.setattr(sim.objects, "load_object", no_parsing_here)
    monkeypatch.setattr(sim.camera, "load_object", no_parsing_here)
    folder = tmp_path / "objects"
    folder.mkdir()
    with open(folder / "huge.stl", "wb") as file:  # sparse: 2 GB of nothing
        file.truncate(2 << 30)
    (folder / "notes.txt").write_text("a shopping list")
    (folder / "fake.ply").write_bytes(b"MZ\x90\x00 not a ply at all")
    import trimesh

    trimesh.creation.box((40, 40, 60)).export(folder / "block.stl")
    with TestClient(create_app(state_dir, object_dir=folder)) as client:
        for name, cause in (("huge.stl", "larger than"), ("notes.txt", "mesh file type"),
                            ("fake.ply", "not a PLY file")):
            response = client.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                           "object": name})
            assert response.status_code == 422, name
            assert cause in _detail(response)
        urls = station_urls()
        created = client.post("/api/v1/scans", json={"plan": capture_plan(2),
                                                     "object": "block.stl", **urls})
        assert created.status_code == 201, created.text
        done = wait_for_state(client, created.json()["id"], "done", "failed")
        assert done["state"] == "done", done["reason"]  # loaded in the child


def test_the_scan_child_loads_its_object_under_a_memory_limit(state_dir, tmp_path):
    import trimesh

    folder = tmp_path / "objects"
    folder.mkdir()
    trimesh.creation.icosphere(6).apply_scale(50).export(folder / "sphere.stl",
                                                         file_type="stl_ascii")
    app = create_app(state_dir, object_dir=folder, object_memory_bytes=8 << 20)
    with TestClient(app) as client:
        created = client.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                     "object": "sphere.stl", **station_urls()})
        assert created.status_code == 201, created.text
        ended = wait_for_state(client, created.json()["id"], "done", "failed", timeout=60)
    assert ended["state"] == "failed"
    assert "memory" in ended["reason"] and str(folder) not in ended["reason"]


# -- 4. 500s that are 4xx ----------------------------------------------------------------------
def test_malformed_values_are_422_not_500(client):
    scans = "/api/v1/scans"
    for plan in ({"angles": [0], "volume": "abc"}, {"angles": [0], "volume": [1, "x", 3]},
                 {"angles": [0], "volume": {"radius_mm": None}},
                 {"reconstruction": {"lam": "x"}}, {"angles": ["a"]}, {"angles": 5},
                 {"angles": "0369"}, {"angles": "90"}, {"angles": {"0": 1, "45": 2}},
                 {"angles": [True, False]}, {"angles": ["1e2", " 7 "]}, {"angles": [None]}):
        response = client.post(scans, json={"plan": plan})
        assert response.status_code == 422, (plan, response.text)
        _detail(response)
    huge = '{"plan": {"angles": [' + "9" * 4000 + "]}}"
    response = client.post(scans, content=huge, headers={"content-type": "application/json"})
    assert response.status_code == 422 and "angles" in _detail(response)
    assert client.get(scans, params={"offset": "99999999999999999999999"}).status_code == 422
    assert client.get(scans, params={"limit": "99999999999999999999999"}).status_code == 422
    scan = client.post(scans, json={"plan": capture_plan(1), **station_urls()}).json()
    events = f"{scans}/{scan['id']}/events"
    assert client.get(events, headers={"Last-Event-ID": "9" * 5000}).status_code == 422
    assert client.get(events, params={"after": "9" * 40}).status_code == 422
    wait_for_state(client, scan["id"], "done")
    assert client.get(events, headers={"Last-Event-ID": "3"}).status_code == 200


# -- 5. every plan field bounded to what a station can do -------------------------------------
@pytest.mark.parametrize("field, value", [
    ("settle_s", 1e300), ("settle_s", 3601), ("frames_per_view", 1_000_000_000),
    ("volume", [1e308, 0, 100]), ("volume", [100, -1e308, 100]), ("voxel_mm", 1e-9),
    ("voxel_mm", 1e6), ("outlier_neighbors", 10**9), ("outlier_std", 1e300),
    ("reconnect_timeout_s", 1e300), ("angles", [1e300]),
    ("angles", [0] * 200_000),  # under the 1 MiB body limit
    ("reconstruction", {"max_neurons": 10**9}), ("reconstruction", {"max_epochs": 10**9}),
    ("reconstruction", {"lam": 1e300}), ("reconstruction", {"depth": 10**6}),
    ("reconstruction", {"max_train_points": 10**12}), ("reconstruction", {"seed": 2**80}),
    ("reconstruction", {"voxel_mm": 1e-12}), ("reconstruction", {"polish_epochs": 10**9}),
])
def test_plan_values_a_station_cannot_do_are_422_naming_the_field(client, field, value):
    plan = capture_plan(2)
    plan[field] = value
    response = client.post("/api/v1/scans", json={"plan": plan})
    assert response.status_code == 422, response.text
    name = field if field != "reconstruction" else "reconstruction." + next(iter(value))
    assert name in _detail(response)


def test_failure_reasons_show_no_server_paths(state_dir):
    class Failing(GatedRunner):
        def start(self):
            self.state = "failed"
            raise RuntimeError(f"no room for the recording in {self.folder}/recording.mcap")

    def factory(plan, *, out_dir, **kwargs):
        runner = Failing(threading.Event())
        runner.folder = out_dir
        return runner

    with TestClient(create_app(state_dir, runner_factory=factory)) as client:
        scan = client.post("/api/v1/scans", json={"plan": capture_plan(1)}).json()
        failed = wait_for_state(client, scan["id"], "failed")
    assert "no room for the recording" in failed["reason"]
    assert str(state_dir) not in failed["reason"] and "/tmp" not in failed["reason"]


# -- 6. bounded work -----------------------------------------------------------------------------
def test_scans_queue_up_to_a_bound_then_429(state_dir):
    with TestClient(create_app(state_dir, max_running=1, max_queued=1)) as client:
        slow = {"plan": capture_plan(40, settle_s=0.2)}
        first = client.post("/api/v1/scans", json={**slow, **station_urls()})
        second = client.post("/api/v1/scans", json={**slow, **station_urls()})
        third = client.post("/api/v1/scans", json={**slow, **station_urls()})
        assert first.status_code == 201 and second.status_code == 201
        assert second.json()["state"] == "queued"
        assert third.status_code == 429 and "Retry-After" in third.headers
        assert "queue" in _detail(third)
        assert client.get("/healthz").json()["queued"] == 1
        client.post(f"/api/v1/scans/{first.json()['id']}/cancel")
        wait_for_state(client, first.json()["id"], "interrupted")
        wait_for_state(client, second.json()["id"], "running", "starting")
        client.post(f"/api/v1/scans/{second.json()['id']}/cancel")
        wait_for_state(client, second.json()["id"], "interrupted")
        # a queued scan can be cancelled before it starts, and resumed (it starts afresh)
        busy = client.post("/api/v1/scans", json={**slow, **station_urls()}).json()
        queued = client.post("/api/v1/scans", json={"plan": capture_plan(2),
                                                     **station_urls()}).json()
        assert queued["state"] == "queued"
        cancelled = client.post(f"/api/v1/scans/{queued['id']}/cancel").json()
        assert cancelled["state"] == "interrupted" and "before it started" in cancelled["reason"]
        client.post(f"/api/v1/scans/{busy['id']}/cancel")
        wait_for_state(client, busy["id"], "interrupted")
        assert client.post(f"/api/v1/scans/{queued['id']}/resume").status_code == 202
        assert wait_for_state(client, queued["id"], "done", "failed")["state"] == "done"


def test_status_answers_do_not_grow_with_the_plan(state_dir):
    gate = threading.Event()
    with TestClient(create_app(state_dir, runner_factory=lambda plan, **kw: GatedRunner(gate))
                    ) as client:
        small = client.post("/api/v1/scans", json={"plan": capture_plan(4)}).json()
        big_plan = capture_plan(3600)
        big = client.post("/api/v1/scans", json={"plan": big_plan}).json()
        sizes = [len(client.get(f"/api/v1/scans/{s['id']}").content) for s in (small, big)]
        assert abs(sizes[1] - sizes[0]) < 100, sizes
        listed = client.get("/api/v1/scans").content
        assert len(listed) < 4000
        full = client.get(f"/api/v1/scans/{big['id']}/plan").json()
        assert full["angles"] == big_plan["angles"]
        assert client.get(f"/api/v1/scans/{big['id']}").json()["plan"]["n_views"] == 3600
        gate.set()
        for scan in (small, big):
            wait_for_state(client, scan["id"], "running")
            client.post(f"/api/v1/scans/{scan['id']}/cancel")


def test_healthz_answers_while_a_post_waits_for_a_slow_child(state_dir):
    """With a real uvicorn server: a POST whose child hangs does not hold other requests."""
    import httpx

    with socket.socket() as listener, LiveServer(create_app(state_dir)) as server:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        url = f"socket://127.0.0.1:{listener.getsockname()[1]}?timeout=5"
        with httpx.Client(base_url=server.url, timeout=10) as http:
            created = http.post("/api/v1/scans", json={"plan": capture_plan(1),
                                                       "turntable_url": url})
            assert created.status_code == 201 and created.json()["state"] == "starting"
            assert http.get("/healthz").status_code == 200
            scan_id = created.json()["id"]
            wait_until(lambda: http.get(f"/api/v1/scans/{scan_id}").json()["state"]
                       == "failed", 60, what="the scan to fail")
