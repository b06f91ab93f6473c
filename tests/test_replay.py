"""Replay: a recording acts as the station; the same seed gives the same mesh as the live scan,
and an interrupted scan resumes from its recording into a new segment."""

import dataclasses
import uuid

import numpy as np
import pytest
import trimesh

from capture.plan import ScanPlan
from capture.recording import read_recording, segment_paths
from capture.replay import ReplayCamera, replay_plan, replay_runner, replay_station
from capture.runner import ScanRunner
from drivers.errors import DeviceError
from tests.test_engine import FAST

CAMERA = "sim://camera?width=320&height=200&object=vase"
PLAN = ScanPlan.turn(8, frames_per_view=2, settle_s=0.0, reconstruction=FAST)


def live_scan(out_dir, scan_plan=PLAN, **kwargs):
    station = f"replay-{uuid.uuid4().hex[:8]}"
    runner = ScanRunner(scan_plan, camera_url=f"{CAMERA}&station={station}",
                        turntable_url=f"sim://turntable?instant=1&station={station}",
                        out_dir=out_dir, **kwargs)
    return runner


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    out = tmp_path_factory.mktemp("live")
    runner = live_scan(out)
    assert runner.start().wait(timeout=300) == "done", runner.reason
    return runner


def test_replay_gives_the_live_mesh_exactly(live, tmp_path):
    replay = replay_runner(live.out_dir, tmp_path / "replayed", workers=2)
    assert replay.start().wait(timeout=300) == "done", replay.reason
    assert not (tmp_path / "replayed" / "recording.mcap").exists()  # replays do not record
    live_mesh = trimesh.load(live.out_dir / "mesh.ply", process=False)
    replayed = trimesh.load(tmp_path / "replayed" / "mesh.ply", process=False)
    np.testing.assert_array_equal(replayed.vertices, live_mesh.vertices)
    np.testing.assert_array_equal(replayed.faces, live_mesh.faces)
    live_meshes = [d.figures["faces"] for d in live.documents if d.kind == "mesh"]
    assert [d.figures["faces"] for d in replay.documents if d.kind == "mesh"] == live_meshes


def test_replay_with_another_lambda_changes_only_the_meshing(live, tmp_path):
    replay = replay_runner(live.out_dir / "recording.mcap", tmp_path / "lam", lam=5.0)
    assert replay.plan.reconstruction.lam == 5.0 and replay.plan.settle_s == 0.0
    assert replay.start().wait(timeout=300) == "done"
    figures = [d.figures for d in replay.documents if d.kind == "mesh"][-1]
    live_figures = [d.figures for d in live.documents if d.kind == "mesh"][-1]
    assert figures["faces"] != live_figures["faces"]


def test_replay_devices_follow_the_recording_and_refuse_other_angles(live):
    recording = read_recording(live.out_dir)
    station = replay_station(recording)
    with pytest.raises(DeviceError, match="grab before the first move"):
        station.camera.grab()
    with pytest.raises(DeviceError, match="next view is at 0°, not 45°"):
        station.turntable.move_to(45.0)
    station.turntable.move_to(0.0)
    assert station.turntable.angle == recording.views[0].measured_angle_deg
    np.testing.assert_array_equal(station.camera.grab().depth, recording.views[0].frames[0])
    assert isinstance(station.camera, ReplayCamera)
    empty = dataclasses.replace(recording, views=[])
    with pytest.raises(ValueError, match="holds no complete view"):
        replay_plan(empty)


def test_an_interrupted_scan_resumes_into_a_new_segment(tmp_path):
    out = tmp_path / "scan"
    first = live_scan(out, dataclasses.replace(PLAN, reconstruction=None))

    def stop_after_three(document):
        if document.kind == "progress" and document.views_done == 3:
            first.cancel()

    first.subscribe(stop_after_three)
    assert first.start().wait(timeout=60) == "interrupted"
    old = (out / "recording.mcap").read_bytes()
    resumed = ScanRunner.resume_recording(out)
    assert resumed.start().wait(timeout=60) == "done", resumed.reason
    assert resumed.documents[0].resumed_views == 3 and resumed.documents[0].segment == 2
    assert [p.name for p in segment_paths(out)] == ["recording.mcap", "recording-2.mcap"]
    assert (out / "recording.mcap").read_bytes() == old  # the old segment is never rewritten
    recording = read_recording(out)
    assert [v.index for v in recording.views] == list(range(8))
    assert recording.complete


def test_replay_of_a_resumed_scan_gives_its_final_mesh(tmp_path):
    out = tmp_path / "scan"
    first = live_scan(out)
    first.subscribe(lambda d: d.kind == "progress" and d.views_done == 4 and first.cancel())
    assert first.start().wait(timeout=300) == "interrupted"
    resumed = ScanRunner.resume_recording(out)
    assert resumed.start().wait(timeout=300) == "done", resumed.reason
    assert len(segment_paths(out)) == 2
    replay = replay_runner(out, tmp_path / "replayed")
    assert replay.start().wait(timeout=300) == "done", replay.reason
    live_mesh = trimesh.load(out / "mesh.ply", process=False)
    replayed = trimesh.load(tmp_path / "replayed" / "mesh.ply", process=False)
    np.testing.assert_array_equal(replayed.vertices, live_mesh.vertices)
    np.testing.assert_array_equal(replayed.faces, live_mesh.faces)
