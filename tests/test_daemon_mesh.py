"""Meshes through the daemon: a real (small) reconstruction, downloads in four formats, refine
through ONNX with no retraining, and re-processing from the recording."""

from __future__ import annotations

import io
import json
import threading

import numpy as np
import pytest
import trimesh
from daemon_helpers import (
    MESH_CAMERA,
    capture_plan,
    mesh_plan,
    station_urls,
    wait_for_state,
    wait_until,
)
from fastapi.testclient import TestClient

from capture.daemon.app import create_app


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    """(state dir, scan JSON) of one 6-view scan reconstructed by the real engine."""
    state_dir = tmp_path_factory.mktemp("daemon") / "state"
    with TestClient(create_app(state_dir)) as client:
        body = {"plan": mesh_plan(6), **station_urls(**MESH_CAMERA)}
        scan = client.post("/api/v1/scans", json=body).json()
        done = wait_for_state(client, scan["id"], "done", "failed", timeout=300)
    assert done["state"] == "done", done["reason"]
    return state_dir, done


@pytest.fixture
def finished(scanned):
    """(client, scan, state dir): a daemon started on the state dir holding the scan."""
    state_dir, scan = scanned
    with TestClient(create_app(state_dir)) as client:
        yield client, client.get(f"/api/v1/scans/{scan['id']}").json(), state_dir


def load(content: bytes, fmt: str) -> trimesh.Trimesh:
    return trimesh.load(io.BytesIO(content), file_type=fmt, force="mesh", process=False)


def test_the_mesh_downloads_in_four_formats(finished):
    client, scan, _ = finished
    assert scan["files"]["mesh"] and scan["mesh_version"] >= 1
    meshes = {}
    for fmt in ("ply", "obj", "stl", "glb"):
        answer = client.get(f"/api/v1/scans/{scan['id']}/mesh", params={"format": fmt})
        assert answer.status_code == 200, fmt
        assert answer.headers["content-disposition"].endswith(f'.{fmt}"')
        meshes[fmt] = load(answer.content, fmt)
    faces = len(meshes["ply"].faces)
    assert faces > 500
    assert all(len(mesh.faces) == faces for mesh in meshes.values())
    bounds = meshes["ply"].bounds
    for fmt in ("obj", "stl", "glb"):
        assert np.allclose(meshes[fmt].bounds, bounds, atol=1e-3), fmt


def test_refine_makes_new_mesh_versions_without_retraining(finished):
    client, scan, state_dir = finished
    scan_id = scan["id"]
    before = client.get(f"/api/v1/scans/{scan_id}/mesh").content
    engine_files = sorted((state_dir / "scans" / scan_id / "engine").iterdir())
    stamps = [path.stat().st_mtime_ns for path in engine_files]

    refined = client.post(f"/api/v1/scans/{scan_id}/refine", json={"lam": 6.0})
    assert refined.status_code == 200, refined.text
    first = refined.json()
    assert first["mesh_version"] == scan["mesh_version"] + 1
    assert first["mesh_params"] == {"lam": 6.0, "depth": 2, "file": "mesh-lam6-depth2.ply"}
    after = client.get(f"/api/v1/scans/{scan_id}/mesh").content
    assert after != before
    second = client.post(f"/api/v1/scans/{scan_id}/refine", json={"depth": 3}).json()
    assert second["mesh_version"] == first["mesh_version"] + 1
    assert second["mesh_params"]["lam"] == 6.0 and second["mesh_params"]["depth"] == 3
    # the networks were not touched: only meshed again
    assert [p.stat().st_mtime_ns for p in engine_files] == stamps
    text = client.get(f"/api/v1/scans/{scan_id}/events").text
    docs = [json.loads(line[6:]) for line in text.splitlines() if line.startswith("data: ")]
    refines = [d for d in docs if d["kind"] == "refined"]
    assert [d["version"] for d in refines][-2:] == [first["mesh_version"], second["mesh_version"]]
    assert refines[-1]["figures"]["refined"] is True


def test_refine_needs_a_saved_reconstruction(finished):
    client, _, _ = finished
    body = {"plan": capture_plan(2), **station_urls()}
    scan = client.post("/api/v1/scans", json=body).json()
    wait_for_state(client, scan["id"], "done")
    answer = client.post(f"/api/v1/scans/{scan['id']}/refine", json={"lam": 2})
    assert answer.status_code == 409
    assert "no saved reconstruction" in answer.json()["detail"]


def test_reprocess_rebuilds_the_mesh_from_the_recording(finished):
    client, scan, _ = finished
    scan_id = scan["id"]
    answer = client.post(f"/api/v1/scans/{scan_id}/reprocess")
    assert answer.status_code == 202
    assert answer.json()["state"] in ("queued", "starting", "processing", "done")
    done = wait_for_state(client, scan_id, "done", "failed", timeout=300)
    assert done["state"] == "done", done["reason"]
    assert done["mesh_params"]["file"] == "mesh.ply"
    assert done["files"]["recording_segments"] == 1  # re-processing records nothing
    mesh = load(client.get(f"/api/v1/scans/{scan_id}/mesh").content, "ply")
    assert len(mesh.faces) > 500
    # the re-processed reconstruction refines (the refiner dropped the one it had cached)
    refined = client.post(f"/api/v1/scans/{scan_id}/refine", json={"lam": 5.0})
    assert refined.status_code == 200, refined.text
    assert refined.json()["mesh_version"] == done["mesh_version"] + 1


def test_no_reprocess_resume_or_delete_while_a_refine_runs(finished):
    client, scan, _ = finished
    jobs = client.app.app.state.jobs
    real, started, release = jobs.refiner.remesh, threading.Event(), threading.Event()

    def slow_remesh(*args):
        started.set()
        release.wait(30)
        return real(*args)

    jobs.refiner.remesh = slow_remesh
    answers = []
    worker = threading.Thread(target=lambda: answers.append(client.post(
        f"/api/v1/scans/{scan['id']}/refine", json={"lam": 3.0})))
    worker.start()
    try:
        assert started.wait(30)
        for answer in (client.post(f"/api/v1/scans/{scan['id']}/reprocess"),
                       client.delete(f"/api/v1/scans/{scan['id']}")):
            assert answer.status_code == 409
            assert "being refined" in answer.json()["detail"]
    finally:
        release.set()
        worker.join(60)
        jobs.refiner.remesh = real
    assert answers[0].status_code == 200, answers[0].text
    assert client.post(f"/api/v1/scans/{scan['id']}/refine", json={"lam": 2.0}).status_code == 200


def test_two_refines_of_a_scan_store_in_the_order_they_ran(finished):
    """The second refine starts once the first stored its mesh: the current mesh is the last
    one made, and a refine given only λ takes the depth the first one set."""
    client, scan, _ = finished
    jobs = client.app.app.state.jobs
    real, calls, release = jobs.refiner.remesh, [], threading.Event()

    def held_remesh(scan_id, folder, lam, depth):
        calls.append((lam, depth))
        if len(calls) == 1:
            release.wait(30)
        return real(scan_id, folder, lam, depth)

    jobs.refiner.remesh = held_remesh
    before = client.get(f"/api/v1/scans/{scan['id']}").json()["mesh_version"]
    answers = []
    try:
        first = threading.Thread(target=lambda: answers.append(client.post(
            f"/api/v1/scans/{scan['id']}/refine", json={"lam": 3.0, "depth": 3})))
        first.start()
        wait_until(lambda: len(calls) == 1, what="the first refine")
        second = threading.Thread(target=lambda: answers.append(client.post(
            f"/api/v1/scans/{scan['id']}/refine", json={"lam": 2.0})))
        second.start()
        second.join(0.5)
        assert len(calls) == 1  # the second waits for the first
        release.set()
        first.join(60)
        second.join(60)
    finally:
        release.set()
        jobs.refiner.remesh = real
    assert [a.status_code for a in answers] == [200, 200]
    assert calls == [(3.0, 3), (2.0, 3)]
    now = client.get(f"/api/v1/scans/{scan['id']}").json()
    assert now["mesh_version"] == before + 2
    assert (now["mesh_params"]["lam"], now["mesh_params"]["depth"]) == (2.0, 3)


def test_a_refine_that_fails_is_422_with_the_cause_and_keeps_the_mesh(finished):
    client, scan, _ = finished
    scan_id = scan["id"]
    before = client.get(f"/api/v1/scans/{scan_id}").json()
    mesh = client.get(f"/api/v1/scans/{scan_id}/mesh").content
    answer = client.post(f"/api/v1/scans/{scan_id}/refine", json={"lam": 1000})
    assert answer.status_code == 422, answer.text
    detail = answer.json()["detail"]
    assert "boundary spline collapsed" in detail and "previous mesh is kept" in detail
    after = client.get(f"/api/v1/scans/{scan_id}").json()
    assert after["mesh_version"] == before["mesh_version"]
    assert after["mesh_params"] == before["mesh_params"]
    assert client.get(f"/api/v1/scans/{scan_id}/mesh").content == mesh
    again = client.post(f"/api/v1/scans/{scan_id}/refine", json={"lam": 4.0})
    assert again.status_code == 200, again.text  # the refiner is still usable


def test_a_damaged_saved_reconstruction_is_409_saying_so(finished, tmp_path):
    import shutil

    from capture.daemon.errors import Conflict
    from capture.daemon.refine import MeshRefiner

    _, scan, state_dir = finished
    folder = shutil.copytree(state_dir / "scans" / scan["id"], tmp_path / "scan")
    saved = sorted((folder / "engine").glob("*.npz"))
    assert saved
    saved[0].write_bytes(saved[0].read_bytes()[:1000])  # torn
    with pytest.raises(Conflict, match="damaged or of another version: re-process"):
        MeshRefiner().remesh("copy", folder, 2.0, None)
    meta = json.loads((folder / "engine" / "engine.json").read_text())
    meta["params"]["renamed_in_a_later_version"] = 1
    (folder / "engine" / "engine.json").write_text(json.dumps(meta))
    with pytest.raises(Conflict, match="damaged or of another version"):
        MeshRefiner().remesh("copy2", folder, 2.0, None)


def test_a_scan_folder_keeps_only_the_newest_refined_meshes(finished, tmp_path):
    import shutil

    from capture.daemon.refine import KEEP_REFINED, MeshRefiner

    _, scan, state_dir = finished
    folder = shutil.copytree(state_dir / "scans" / scan["id"], tmp_path / "scan")
    refiner = MeshRefiner()
    names = [refiner.remesh("copy", folder, lam, None).file
             for lam in np.linspace(2.0, 6.0, KEEP_REFINED + 3)]
    left = sorted(path.name for path in folder.glob("mesh-lam*-depth*.ply"))
    assert left == sorted(names[-KEEP_REFINED:])
    assert (folder / "mesh.ply").exists()


@pytest.mark.parametrize("body", [{"lam": True}, {"lam": "2"}, {"depth": True}, {"depth": "3"},
                                  {"depth": 2.5}])
def test_a_refine_takes_numbers_only(finished, body):
    client, scan, _ = finished
    answer = client.post(f"/api/v1/scans/{scan['id']}/refine", json=body)
    assert answer.status_code == 422, answer.text
    assert next(iter(body)) in answer.text
