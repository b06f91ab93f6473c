"""Replay: the runner re-runs a recording with no device; the same seed gives the same mesh as
the live scan, and an interrupted scan resumes from its recording into a new segment."""

import dataclasses
import uuid

import numpy as np
import pytest
import trimesh

from capture.plan import ScanPlan
from capture.recording import read_recording, segment_paths
from capture.replay import replay_plan, replay_runner
from capture.runner import ScanRunner

CAMERA = "sim://camera?width=320&height=200&object=vase"


@pytest.fixture(scope="module")
def plan(fast_params):
    return ScanPlan.turn(8, frames_per_view=2, settle_s=0.0, reconstruction=fast_params)


def live_scan(out_dir, scan_plan, **kwargs):
    station = f"replay-{uuid.uuid4().hex[:8]}"
    runner = ScanRunner(scan_plan, camera_url=f"{CAMERA}&station={station}",
                        turntable_url=f"sim://turntable?instant=1&station={station}",
                        out_dir=out_dir, **kwargs)
    return runner


@pytest.fixture(scope="module")
def live(tmp_path_factory, plan):
    out = tmp_path_factory.mktemp("live")
    runner = live_scan(out, plan)
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


def test_replay_announces_the_recorded_views_without_devices(live, tmp_path):
    recording = read_recording(live.out_dir)
    replay = replay_runner(recording, tmp_path / "views", schedule=[])
    assert replay.start().wait(timeout=300) == "done", replay.reason
    assert replay.station.camera is None and replay.station.turntable is None
    assert replay.station.describe() == {**live.station.describe(),
                                         "turntable": "replay://turntable"}
    views = [d for d in replay.documents if d.kind == "view"]
    live_views = [d for d in live.documents if d.kind == "view"]
    assert [v.to_dict() | {"seq": 0, "time": 0} for v in views] == [
        v.to_dict() | {"seq": 0, "time": 0} for v in live_views]
    for view, recorded in zip(views, recording.views, strict=True):
        np.testing.assert_array_equal(np.stack(view.frames), np.stack(recorded.frames))
    assert replay.documents[0].resumed_views == 0
    assert [d.views_done for d in replay.documents if d.kind == "progress"] == list(range(1, 9))
    empty = dataclasses.replace(recording, views=[])
    with pytest.raises(ValueError, match="holds no complete view"):
        replay_plan(empty)


def test_an_interrupted_scan_resumes_into_a_new_segment(tmp_path, plan):
    out = tmp_path / "scan"
    first = live_scan(out, dataclasses.replace(plan, reconstruction=None))

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


def test_replay_of_a_resumed_scan_gives_its_final_mesh(tmp_path, plan):
    out = tmp_path / "scan"
    first = live_scan(out, plan)
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
