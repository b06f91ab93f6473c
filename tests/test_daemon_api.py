"""The daemon's HTTP API on the real runner and simulated stations (capture-only scans)."""

from __future__ import annotations

import json
import os
import re

import pytest
from daemon_helpers import capture_plan, station_urls, wait_for_state, wait_until
from fastapi.testclient import TestClient

from capture.daemon.app import create_app
from capture.recording import read_recording

MCAP_MAGIC = b"\x89MCAP0\r\n"


def start(client, views=4, settle_s=0.0, urls=None, **plan_fields) -> dict:
    body = {"plan": capture_plan(views, settle_s, **plan_fields), **(urls or station_urls())}
    response = client.post("/api/v1/scans", json=body)
    assert response.status_code == 201, response.text
    return response.json()


def test_a_scan_runs_to_done_and_offers_its_recording_and_report(client, tmp_path):
    scan = start(client, views=4)
    assert re.fullmatch(r"[0-9a-f]{16}", scan["id"])
    assert scan["state"] in ("queued", "starting")  # answered before the devices open
    done = wait_for_state(client, scan["id"], "done", "failed")
    assert done["state"] == "done", done["reason"]
    assert done["progress"] == {"views_done": 4, "views_total": 4, "fraction": 1.0}
    assert done["files"] == {"mesh": False, "recording_segments": 1, "report": True}
    assert done["plan"]["n_views"] == 4 and "angles" not in done["plan"]
    assert client.get(f"/api/v1/scans/{scan['id']}/plan").json()["angles"] == \
        [0.0, 90.0, 180.0, 270.0]

    recording = client.get(f"/api/v1/scans/{scan['id']}/recording")
    assert recording.status_code == 200
    assert recording.content.startswith(MCAP_MAGIC)
    assert scan["id"] in recording.headers["content-disposition"]
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(recording.content)
    assert [v.angle_deg for v in read_recording(copy).views] == [0.0, 90.0, 180.0, 270.0]

    report = client.get(f"/api/v1/scans/{scan['id']}/report").json()
    assert report["state"] == "done" and report["views_done"] == 4
    mesh = client.get(f"/api/v1/scans/{scan['id']}/mesh")
    assert mesh.status_code == 404 and "no mesh" in mesh.json()["detail"]
    assert client.get(f"/api/v1/scans/{scan['id']}/recording?segment=2").status_code == 404
    listed = client.get("/api/v1/scans").json()["scans"]
    assert [s["id"] for s in listed] == [scan["id"]]


def test_one_scan_per_device_and_many_stations_at_once(client):
    urls = station_urls()
    first = start(client, views=30, settle_s=0.2, urls=urls)
    busy = client.post("/api/v1/scans", json={"plan": capture_plan(2), **urls})
    assert busy.status_code == 409
    assert "busy with scan " + first["id"] in busy.json()["detail"]
    devices = client.get("/api/v1/devices").json()
    held = {entry["device"]: entry["scan"] for entry in devices["busy"]}
    assert held and set(held.values()) == {first["id"]}

    other = start(client, views=2)  # another station: free
    assert wait_for_state(client, other["id"], "done")["state"] == "done"
    assert client.post(f"/api/v1/scans/{first['id']}/cancel").status_code == 202
    wait_for_state(client, first["id"], "interrupted")
    again = start(client, views=2, urls=urls)  # the devices are free again
    assert wait_for_state(client, again["id"], "done")["state"] == "done"
    assert client.get("/api/v1/devices").json()["busy"] == []


def test_pause_resume_and_cancel_follow_the_state_table(client):
    scan = start(client, views=40, settle_s=0.1)
    scan_id = scan["id"]
    wait_for_state(client, scan_id, "running")
    assert client.post(f"/api/v1/scans/{scan_id}/pause").status_code == 202
    paused = wait_for_state(client, scan_id, "paused")
    assert paused["reason"] == "paused by the user"
    assert client.post(f"/api/v1/scans/{scan_id}/resume").status_code == 202
    wait_for_state(client, scan_id, "running")
    assert client.post(f"/api/v1/scans/{scan_id}/cancel").status_code == 202
    ended = wait_for_state(client, scan_id, "interrupted", "done")
    assert ended["state"] == "interrupted"
    assert ended["reason"] == "cancelled by the user"
    for action in ("pause", "cancel", "refine"):
        answer = client.post(f"/api/v1/scans/{scan_id}/{action}", json={})
        assert answer.status_code == 409, action


def test_an_interrupted_scan_survives_a_restart_and_resumes_from_its_last_view(state_dir):
    with TestClient(create_app(state_dir)) as client:
        scan = start(client, views=12, settle_s=0.15)
        wait_until(lambda: client.get(f"/api/v1/scans/{scan['id']}").json()["progress"]
                   ["views_done"] >= 2, what="two views")
    # the daemon stopped under the scan: it is interrupted, its views recorded
    with TestClient(create_app(state_dir)) as client:
        stopped = client.get(f"/api/v1/scans/{scan['id']}").json()
        assert stopped["state"] == "interrupted"
        recorded = stopped["progress"]["views_done"]
        assert 2 <= recorded < 12
        folder = state_dir / "scans" / scan["id"]
        assert len(read_recording(folder).views) == recorded
        assert client.post(f"/api/v1/scans/{scan['id']}/resume").status_code == 202
        done = wait_for_state(client, scan["id"], "done", "failed")
        assert done["state"] == "done", done["reason"]
        assert done["files"]["recording_segments"] == 2
        views = read_recording(folder).views
        assert sorted(v.index for v in views) == list(range(12))  # each view once


def test_delete_refuses_an_active_scan_and_removes_an_ended_one(client, state_dir):
    scan = start(client, views=30, settle_s=0.2)
    assert client.delete(f"/api/v1/scans/{scan['id']}").status_code == 409
    wait_for_state(client, scan["id"], "running")
    client.post(f"/api/v1/scans/{scan['id']}/cancel")
    wait_for_state(client, scan["id"], "interrupted")
    folder = state_dir / "scans" / scan["id"]
    assert folder.is_dir()
    assert client.delete(f"/api/v1/scans/{scan['id']}").status_code == 204
    assert not folder.exists()
    assert client.get(f"/api/v1/scans/{scan['id']}").status_code == 404
    assert client.delete(f"/api/v1/scans/{scan['id']}").status_code == 404


@pytest.mark.parametrize("body, cause", [
    ({"plan": {"angles": []}}, "the plan has no views (angles is empty)"),
    ({"plan": {"frames_per_view": 0}}, "frames_per_view must be a whole number >= 1"),
    ({"plan": {"bogus": 1}}, "unknown plan field(s): bogus"),
    ({"plan": []}, "plan"),
    ({"camera_url": "foo://x"}, "no camera backend for 'foo://x'"),
    ({"camera_url": "sim://camera?width=abc"}, "width"),
    ({"turntable_url": "sim://turntable?bogus=1"}, "bogus"),
    ({"object": "/no/such/mesh.stl"}, "--object-dir"),  # files: the operator's folder only
    ({"object": ""}, "object"),
    ({"colour": "red"}, "colour"),
])
def test_bad_input_is_422_with_one_line_naming_the_cause(client, body, cause):
    response = client.post("/api/v1/scans", json=body)
    assert response.status_code == 422
    detail = response.json()["detail"]
    assert cause in detail and "\n" not in detail
    assert client.get("/api/v1/scans").json()["scans"] == []  # nothing was created


def test_malformed_json_and_ids(client):
    response = client.post("/api/v1/scans", content=b"{not json",
                           headers={"content-type": "application/json"})
    assert response.status_code == 422 and "JSON" in response.json()["detail"]
    assert client.get("/api/v1/scans/0123456789abcdef").status_code == 404
    assert client.get("/api/v1/scans/NOT-AN-ID").status_code == 422
    assert client.get("/api/v1/scans/..%2F..%2Fetc").status_code in (404, 422)
    scan = start(client, views=1)
    assert client.get(f"/api/v1/scans/{scan['id']}/mesh?format=exe").status_code == 422
    assert client.post(f"/api/v1/scans/{scan['id']}/refine", json={"lam": -1}).status_code == 422
    wait_for_state(client, scan["id"], "done")


def test_request_bodies_are_size_limited(state_dir):
    with TestClient(create_app(state_dir, max_body_bytes=2000)) as client:
        big = {"plan": capture_plan(2), "object": "x" * 900, "camera_url": "y" * 1500}
        assert client.post("/api/v1/scans", json=big).status_code == 413

        def chunks():  # no Content-Length: counted as it arrives
            for _ in range(10):
                yield b" " * 500

        response = client.post("/api/v1/scans", content=chunks(),
                               headers={"content-type": "application/json"})
        assert response.status_code == 413
        assert "larger than 2000 bytes" in response.json()["detail"]
        assert client.get("/api/v1/scans").json()["scans"] == []


def test_download_names_cannot_escape_the_state_dir(client, state_dir, tmp_path):
    scan = start(client, views=1)
    wait_for_state(client, scan["id"], "done")
    secret = tmp_path / "secret.ply"
    secret.write_text("not for download")
    store = _store(client)
    store.update(scan["id"], mesh_params={"file": "../../../secret.ply"})
    assert client.get(f"/api/v1/scans/{scan['id']}/mesh").status_code == 404
    store.update(scan["id"], mesh_params={"file": str(secret)})
    assert client.get(f"/api/v1/scans/{scan['id']}/mesh").status_code == 404
    store.update(scan["id"], out_dir="scans/../..")
    assert client.get(f"/api/v1/scans/{scan['id']}/report").status_code == 404
    store.update(scan["id"], out_dir=f"scans/{scan['id']}")
    report = state_dir / "scans" / scan["id"] / "scan.json"
    report.unlink()
    os.symlink(secret, report)  # a link planted in the scan folder leads outside
    assert client.get(f"/api/v1/scans/{scan['id']}/report").status_code == 404


def _store(client):
    return client.app.app.state.jobs.store  # BodySizeLimit wraps the FastAPI app


def test_devices_list_backends_and_status(client):
    devices = client.get("/api/v1/devices").json()
    kinds = {(b["kind"], b["scheme"]): b for b in devices["backends"]}
    assert kinds[("camera", "sim")]["status"] == "available"
    assert kinds[("turntable", "sim")]["status"] == "available"
    assert devices["busy"] == []


def test_docs_page_and_assets_are_served_locally(client):
    schema = client.get("/openapi.json").json()
    for path in ("/api/v1/devices", "/api/v1/scans", "/api/v1/scans/{scan_id}",
                 "/api/v1/scans/{scan_id}/refine", "/api/v1/scans/{scan_id}/mesh",
                 "/api/v1/scans/{scan_id}/events", "/healthz"):
        assert path in schema["paths"]
    assert set(schema["paths"]["/api/v1/scans/{scan_id}"]) == {"get", "delete"}
    docs = client.get("/docs").text
    assert "/static/vendor/swagger-ui-bundle.js" in docs
    page = client.get("/").text
    script = client.get("/static/app.js").text
    for text in (docs, page, script):
        assert not re.search(r"(src|href)=\"https?://", text)  # no CDN
        assert "cdn." not in text
    for asset in ("vendor/swagger-ui-bundle.js", "vendor/swagger-ui.css",
                  "vendor/three-viewer.min.js", "style.css"):
        assert client.get(f"/static/{asset}").status_code == 200
    assert client.get("/healthz").json()["status"] == "ok"
    assert json.loads(client.get("/healthz").content)["token_required"] is False
