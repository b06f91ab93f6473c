"""The scan runner on the simulated station: state table, documents, pause / resume / cancel,
lost devices (the simulators' fault knobs), and output checks before the first move."""

import dataclasses
import json
import threading
import uuid

import numpy as np
import pytest
from scan_helpers import CAMERA, FAST_PARAMS, plan

from capture.combine import combine_depths
from capture.lifecycle import Cancelled, RunLifecycle
from capture.plan import PlanError, ScanPlan
from capture.recording import read_recording
from capture.runner import TRANSITIONS, CaptureError, InvalidTransition, ScanRunner
from capture.volume import Cylinder
from sim.station import get_station


def station_name():
    return f"test-{uuid.uuid4().hex[:8]}"


def runner_for(tmp_path, scan_plan, table_options="", camera_options="", **kwargs):
    name = station_name()
    runner = ScanRunner(
        scan_plan,
        camera_url=f"{CAMERA}&station={name}{camera_options}",
        turntable_url=f"sim://turntable?instant=1&station={name}{table_options}",
        out_dir=tmp_path / "scan",
        **kwargs,
    )
    runner.station_name = name
    return runner


def kinds(runner):
    return [d.kind for d in runner.documents]


def test_a_scan_emits_start_views_progress_stop_in_order(tmp_path):
    runner = runner_for(tmp_path, plan(4))
    seen = []
    unsubscribe = runner.subscribe(seen.append)
    assert runner.state == "idle"
    assert runner.start().wait(timeout=60) == "done"
    unsubscribe()
    assert kinds(runner) == ["start"] + ["view", "progress"] * 4 + ["stop"]
    assert seen == runner.documents
    assert [d.seq for d in runner.documents] == list(range(len(runner.documents)))
    views = [d for d in runner.documents if d.kind == "view"]
    assert [v.angle_deg for v in views] == [0.0, 90.0, 180.0, 270.0]
    np.testing.assert_allclose([v.measured_angle_deg for v in views], [0, 90, 180, 270],
                               atol=0.01)
    assert all(v.n_frames == 2 and len(v.frames) == 2 and v.valid_pixels > 0 for v in views)
    stop = runner.documents[-1].to_dict()
    assert stop["state"] == "done" and stop["views_done"] == 4
    assert "frames" not in views[0].to_dict()  # raw frames stay out of the JSON documents
    recording = read_recording(tmp_path / "scan")
    assert recording.complete and [v.index for v in recording.views] == [0, 1, 2, 3]
    np.testing.assert_array_equal(recording.views[2].frames[1], views[2].frames[1])


def test_no_document_follows_the_stop(tmp_path):
    """A fit running when a scan is cancelled or fails ends after the stop document: its mesh
    is not published (the scan's files and scan.json are the stop's)."""
    runner = runner_for(tmp_path, plan(2))
    assert runner.start().wait(timeout=60) == "done"
    count = len(runner.documents)
    runner._on_mesh(None, {"version": 7, "views": 2})  # as the engine's thread would call it
    assert len(runner.documents) == count and runner.documents[-1].kind == "stop"


def test_a_cancel_does_not_wait_for_the_fit_under_way(tmp_path, monkeypatch):
    """The fit running when a scan is cancelled is abandoned: the scan ends and closes its
    devices without waiting for it (a vase's live scan waited 2-5 s)."""
    from capture.live.engine import IncrementalEngine

    fitting, release = threading.Event(), threading.Event()

    def held_fit(engine, update):
        fitting.set()
        release.wait(60)

    monkeypatch.setattr(IncrementalEngine, "_run", held_fit)
    runner = runner_for(tmp_path, plan(6, reconstruction=dataclasses.replace(
        FAST_PARAMS, update_every=1)))
    runner.start()
    try:
        assert fitting.wait(60)
        runner.cancel()
        ended = []
        waiter = threading.Thread(target=lambda: ended.append(runner.wait()), daemon=True)
        waiter.start()
        waiter.join(30)
        assert ended == ["interrupted"]  # while the fit is still held
        assert kinds(runner)[-1] == "stop"
    finally:
        release.set()


def test_invalid_transitions_raise_and_the_table_is_closed(tmp_path):
    runner = runner_for(tmp_path, plan(2))
    with pytest.raises(InvalidTransition, match="cannot resume a scan that is idle"):
        runner.resume()
    with pytest.raises(InvalidTransition, match="cannot pause a scan that is idle"):
        runner.pause()
    runner.start().wait(timeout=60)
    with pytest.raises(InvalidTransition, match="cannot start a scan that is done"):
        runner.start()
    with pytest.raises(InvalidTransition):
        runner.resume()
    states = {s for pair in TRANSITIONS for s in pair[:1]} | set(TRANSITIONS.values())
    assert states == {"idle", "running", "paused", "stopping", "done", "failed", "interrupted"}
    assert not any(src in ("done", "failed", "interrupted") for src, _ in TRANSITIONS)


def test_cancel_before_start_ends_interrupted(tmp_path):
    runner = runner_for(tmp_path, plan(2))
    runner.cancel()
    assert runner.state == "interrupted"


def test_pause_resume_then_cancel_keeps_the_recorded_views(tmp_path):
    runner = runner_for(tmp_path, plan(6))
    paused = threading.Event()

    def on_document(document):
        if document.kind == "progress" and document.views_done == 2:
            runner.pause()
        if document.kind == "paused":
            paused.set()

    runner.subscribe(on_document)
    runner.start()
    assert paused.wait(30) and runner.wait_for_state("paused", timeout=5) == "paused"
    assert kinds(runner)[-1] == "paused"
    runner.resume()
    assert runner.wait_for_state("running", timeout=5) == "running"
    runner.cancel()
    assert runner.wait(timeout=30) == "interrupted"
    docs = kinds(runner)
    assert docs.index("paused") < docs.index("resumed") < docs.index("stop") == len(docs) - 1
    assert runner.documents[-1].reason == "cancelled by the user"
    done = docs.count("view")
    assert 2 <= done < 6
    assert [v.index for v in read_recording(tmp_path / "scan").views] == list(range(done))


class RequestWhileClearing(threading.Event):
    """A request flag whose first clear by the worker (the checkpoint taking a pause) lets
    ``request`` run to its end on another thread first."""

    def __init__(self, request):
        super().__init__()
        self.request, self.worker = request, threading.current_thread()

    def clear(self) -> None:
        if self.request is not None and threading.current_thread() is self.worker:
            request, self.request = self.request, None
            other = threading.Thread(target=request)
            other.start()
            other.join(5.0)
        super().clear()


def paused_at_checkpoint(request, flag: str) -> str:
    """A running lifecycle whose checkpoint takes a pause while ``request`` comes, as it
    clears ``flag``; what the checkpoint did within 10 s: "returned", "cancelled" or "stuck"
    (still paused)."""
    run = RunLifecycle()
    run._transition("start")
    outcome = ["stuck"]

    def worker():
        hooked = RequestWhileClearing(lambda: request(run))
        if getattr(run, flag).is_set():
            hooked.set()
        setattr(run, flag, hooked)
        run.pause()
        try:
            run._checkpoint(0)
            outcome[0] = "returned"
        except Cancelled:
            outcome[0] = "cancelled"

    thread = threading.Thread(target=worker, daemon=True)
    thread.start()
    thread.join(10)
    return outcome[0]


@pytest.mark.parametrize("flag", ["_pause_requested", "_resume_requested"])
def test_a_cancel_or_resume_as_a_pause_is_taken_is_never_lost(flag):
    """A cancel or resume that comes while the checkpoint takes a pause ends it (else its
    resume flag was cleared after it, and the scan stayed paused for good)."""
    assert paused_at_checkpoint(lambda run: run.cancel(), flag) == "cancelled"
    assert paused_at_checkpoint(lambda run: run.resume(), flag) == "returned"


def test_a_pause_asked_just_after_a_resume_holds():
    """resume() then pause() while the scan is still paused (the worker not yet running
    again): it runs on, and pauses at its next checkpoint."""
    run = RunLifecycle()
    run._transition("start")
    run.pause()
    worker = threading.Thread(target=run._checkpoint, args=(0,), daemon=True)
    worker.start()

    def wait_for(state):
        return run.wait_for_state(state, timeout=10) == state

    assert wait_for("paused")
    run.resume()
    run.pause()
    worker.join(10)
    assert not worker.is_alive() and run.state == "running"
    again = threading.Thread(target=run._checkpoint, args=(1,), daemon=True)
    again.start()
    assert wait_for("paused")
    run.resume()
    again.join(10)
    assert run.state == "running"


def test_unplugged_turntable_pauses_reconnects_and_resumes_at_that_view(tmp_path):
    runner = runner_for(tmp_path, plan(5), table_options="&unplug_after_moves=3")
    assert runner.start().wait(timeout=60) == "done"
    paused = [d for d in runner.documents if d.kind == "paused"]
    assert len(paused) == 1 and paused[0].reason == "device"
    assert "turntable disconnected at view 3/5" in paused[0].message
    docs = kinds(runner)
    assert docs.index("paused") + 1 == docs.index("resumed")
    recording = read_recording(tmp_path / "scan")
    assert [v.index for v in recording.views] == [0, 1, 2, 3, 4]  # each once, in order
    np.testing.assert_allclose([v.measured_angle_deg for v in recording.views],
                               [0, 72, 144, 216, 288], atol=0.01)


def test_camera_disconnect_pauses_and_resumes(tmp_path):
    runner = runner_for(tmp_path, plan(4), camera_options="&disconnect_after=5")
    assert runner.start().wait(timeout=60) == "done"
    (paused,) = [d for d in runner.documents if d.kind == "paused"]
    assert paused.view_index == 2 and "camera disconnected" in paused.message
    assert [v.index for v in read_recording(tmp_path / "scan").views] == [0, 1, 2, 3]


def _never_reconnects(runner):
    def refuse(device):
        raise ConnectionError(f"{device} still unplugged")

    def on_document(document):
        if document.kind == "paused":
            runner.station.reconnect = refuse

    return on_document


def test_a_device_that_stays_away_fails_the_scan_and_keeps_the_views(tmp_path):
    scan_plan = plan(5, reconnect_timeout_s=0.2, on_device_lost="fail")
    runner = runner_for(tmp_path, scan_plan, table_options="&unplug_after_moves=3")
    runner.subscribe(_never_reconnects(runner))
    assert runner.start().wait(timeout=60) == "failed"
    assert "turntable did not come back within 0.2 s" in runner.reason
    assert "2 views are recorded" in runner.reason
    assert kinds(runner)[-2:] == ["error", "stop"]
    assert [v.index for v in read_recording(tmp_path / "scan").views] == [0, 1]


def test_wait_policy_stays_paused_until_resume(tmp_path):
    scan_plan = plan(4, reconnect_timeout_s=0.1, on_device_lost="wait")
    runner = runner_for(tmp_path, scan_plan, table_options="&unplug_after_moves=2")
    real_reconnect = None

    def on_document(document):
        nonlocal real_reconnect
        if document.kind == "paused":
            real_reconnect = runner.station.reconnect
            runner.station.reconnect = _refuse

    runner.subscribe(on_document)
    runner.start()
    assert runner.wait_for_state("paused", timeout=30) == "paused"
    assert runner.wait(timeout=0.5) == "paused"  # gave up retrying, still waiting
    runner.station.reconnect = real_reconnect
    runner.resume()
    assert runner.wait(timeout=60) == "done"
    assert [v.index for v in read_recording(tmp_path / "scan").views] == [0, 1, 2, 3]


def _refuse(device):
    raise ConnectionError(f"{device} still unplugged")


def test_unwritable_output_fails_before_anything_moves(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    name = station_name()
    runner = ScanRunner(plan(3), camera_url=f"{CAMERA}&station={name}",
                        turntable_url=f"sim://turntable?instant=1&station={name}",
                        out_dir=blocker / "scan")
    with pytest.raises(CaptureError, match=r"output folder .*file/scan is not writable"):
        runner.start()
    assert runner.state == "failed"
    assert kinds(runner) == ["error", "stop"]
    assert get_station(name).angle_source is None  # the station was never even opened


def test_full_disk_fails_before_the_first_move(tmp_path, monkeypatch):
    import capture.outputs

    class Usage:
        free = 10_000_000

    monkeypatch.setattr(capture.outputs.shutil, "disk_usage", lambda path: Usage)
    runner = runner_for(tmp_path, plan(36))
    with pytest.raises(CaptureError, match=r"not enough space in .*scan: the scan needs about"):
        runner.start()
    assert runner.state == "failed"
    assert get_station(runner.station_name).angle_source.moves == 0


def test_bad_plans_fail_with_one_line():
    with pytest.raises(PlanError, match="frames_per_view must be a whole number >= 1"):
        ScanPlan(frames_per_view=0).validate()
    with pytest.raises(PlanError, match="combine must be one of median, mean, first"):
        ScanPlan(combine="max").validate()
    with pytest.raises(PlanError, match="views must be a whole number"):
        ScanPlan.turn(0)
    with pytest.raises(PlanError, match="unknown plan field"):
        ScanPlan.from_dict({"angles": [0], "speed": 3})
    again = ScanPlan.from_json(ScanPlan.turn(8, settle_s=0.5).to_json())
    assert again == ScanPlan.turn(8, settle_s=0.5)


def test_median_combination_ignores_missing_pixels():
    frames = np.array([[[0, 10, 5, 7]], [[0, 0, 9, 1]], [[0, 30, 6, 4]]], dtype=np.uint16)
    np.testing.assert_array_equal(combine_depths(frames, "median"), [[0, 20, 6, 4]])
    np.testing.assert_array_equal(combine_depths(frames, "mean"), [[0, 20, 7, 4]])
    np.testing.assert_array_equal(combine_depths(frames, "first"), frames[0])
    rng = np.random.default_rng(0)
    stack = rng.integers(1, 2000, (5, 40, 30)).astype(np.uint16)
    np.testing.assert_array_equal(combine_depths(stack), np.median(stack, axis=0))


def test_disk_full_mid_scan_fails_clearly_and_keeps_the_views_already_recorded(
        tmp_path, monkeypatch):
    import errno

    from capture.recording import RecordingWriter

    real_sync, syncs = RecordingWriter._sync, []

    def sync_until_the_disk_fills(self):
        syncs.append(1)
        if len(syncs) > 4:  # metadata, start document, views 0 and 1; view 2 finds no room
            raise OSError(errno.ENOSPC, "No space left on device")
        real_sync(self)

    monkeypatch.setattr(RecordingWriter, "_sync", sync_until_the_disk_fills)
    runner = runner_for(tmp_path, plan(6))
    assert runner.start().wait(timeout=60) == "failed"
    assert "recording to" in runner.reason and "No space left on device" in runner.reason
    assert [v.index for v in read_recording(tmp_path / "scan").views] == [0, 1]
    # view 2 never counted as done: the scan stopped there (resume captures it again)
    assert runner.documents[-1].views_done == 2 and kinds(runner)[-2:] == ["error", "stop"]


def test_a_second_scan_never_lands_in_the_folder_of_the_first(tmp_path):
    assert runner_for(tmp_path, plan(2)).start().wait(timeout=60) == "done"
    second = runner_for(tmp_path, plan(2))
    with pytest.raises(CaptureError, match=r"already holds a scan recording: resume it"):
        second.start()
    assert get_station(second.station_name).angle_source is None  # nothing opened or moved
    assert [v.index for v in read_recording(tmp_path / "scan").views] == [0, 1]


def test_ctrl_c_while_the_devices_open_closes_them_and_ends_the_scan(tmp_path, monkeypatch):
    from capture.outputs import ScanOutputs

    def ctrl_c(*args, **kwargs):  # the step after the station opened
        raise KeyboardInterrupt

    monkeypatch.setattr(ScanOutputs, "check_space", ctrl_c)
    runner = runner_for(tmp_path, plan(2))
    with pytest.raises(KeyboardInterrupt):
        runner.start()
    assert runner.wait(timeout=5) == "failed" and "interrupted while starting" in runner.reason
    assert not runner.station.turntable.is_open  # (its reader thread held the exit for good)


def test_a_new_scan_never_replaces_a_folders_scan_files(tmp_path):
    folder = tmp_path / "scan"
    folder.mkdir()
    (folder / "mesh.ply").write_text("mine")
    (folder / "notes.txt").write_text("mine too")
    runner = runner_for(tmp_path, plan(2))
    with pytest.raises(CaptureError, match=r"already holds mesh.ply, which a new scan would "
                                           r"replace: choose another output folder"):
        runner.start()
    assert (folder / "mesh.ply").read_text() == "mine"
    (folder / "mesh.ply").unlink()  # other files are the user's business
    assert runner_for(tmp_path, plan(2)).start().wait(timeout=60) == "done"
    assert (folder / "notes.txt").read_text() == "mine too"


def test_segments_of_two_scans_are_not_read_as_one(tmp_path):
    import shutil

    from capture.recording import RecordingError

    for name in ("a", "b"):
        assert runner_for(tmp_path / name, plan(2)).start().wait(timeout=60) == "done"
    shutil.copy(tmp_path / "b" / "scan" / "recording.mcap",
                tmp_path / "a" / "scan" / "recording-2.mcap")
    with pytest.raises(RecordingError, match="a segment of another scan"):
        read_recording(tmp_path / "a" / "scan")


def test_a_resumed_scan_keeps_its_scan_id_across_segments(tmp_path):
    runner = runner_for(tmp_path, plan(4))
    runner.subscribe(lambda d: d.kind == "progress" and d.views_done == 2 and runner.cancel())
    assert runner.start().wait(timeout=60) == "interrupted"
    name = station_name()
    resumed = ScanRunner.resume_recording(
        tmp_path / "scan", camera_url=f"{CAMERA}&station={name}",
        turntable_url=f"sim://turntable?instant=1&station={name}")
    assert resumed.start().wait(timeout=60) == "done"
    assert resumed.scan_id == runner.scan_id
    recording = read_recording(tmp_path / "scan")
    assert len(recording.segments) == 2 and recording.scan_id == runner.scan_id
    assert [v.index for v in recording.views] == [0, 1, 2, 3]


def test_a_resume_with_other_views_is_refused_before_anything_moves(tmp_path):
    runner = runner_for(tmp_path, plan(4))
    runner.subscribe(lambda d: d.kind == "progress" and d.views_done == 2 and runner.cancel())
    assert runner.start().wait(timeout=60) == "interrupted"
    name = station_name()
    for other in (plan(8), plan(4, frames_per_view=3)):
        resumed = ScanRunner.resume_recording(
            tmp_path / "scan", plan=other, camera_url=f"{CAMERA}&station={name}",
            turntable_url=f"sim://turntable?instant=1&station={name}")
        with pytest.raises(CaptureError, match="a resumed scan keeps its recorded views"):
            resumed.start()
    assert [v.index for v in read_recording(tmp_path / "scan").views] == [0, 1]
    same = ScanRunner.resume_recording(
        tmp_path / "scan", plan=plan(4), camera_url=f"{CAMERA}&station={name}",
        turntable_url=f"sim://turntable?instant=1&station={name}")
    assert same.start().wait(timeout=60) == "done"


def test_an_object_outside_the_working_volume_fails_in_one_line_and_keeps_the_views(
        tmp_path, caplog):
    above = plan(4, reconstruction=FAST_PARAMS, volume=Cylinder(110.0, 200.0, 250.0))
    runner = runner_for(tmp_path, above)
    assert runner.start().wait(timeout=120) == "failed"
    assert runner.reason == ("no mesh: 0 points in the working volume (radius 110 mm, 200-250 "
                             "mm above the plate) were seen in 1 views or more: is the object "
                             "on the plate and inside it?")
    said = [r.getMessage() for r in caplog.records if "no points in the working" in r.message]
    assert len(said) == 1 and said[0].startswith("view 1/4: ")  # once, not once per view
    assert len(read_recording(tmp_path / "scan").views) == 4


def test_an_object_cut_by_the_working_volume_is_reported(tmp_path, caplog):
    low = plan(4, volume=Cylinder(110.0, 3.0, 50.0))  # the box stands 100 mm tall
    runner = runner_for(tmp_path, low)
    assert runner.start().wait(timeout=60) == "done"
    assert [d.view_limits for d in runner.documents if d.kind == "progress"] == [("roof",)] * 4
    said = [r.getMessage() for r in caplog.records if "reaches" in r.message]
    assert said == ["the object reaches the working volume's top (50 mm above the plate) in 4 "
                    "of 4 views: what lies beyond is not scanned"]
    report = json.loads((tmp_path / "scan" / "scan.json").read_text())
    assert report["limits_reached"] == {"roof": 4}
    whole = runner_for(tmp_path / "whole", plan(4))
    assert whole.start().wait(timeout=60) == "done"
    assert all(d.view_limits == () for d in whole.documents if d.kind == "progress")
