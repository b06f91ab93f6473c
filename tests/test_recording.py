"""MCAP recordings: round trip, torn files, and a scan SIGKILLed at random moments."""

import os
import random
import signal
import subprocess
import sys
import time
import uuid

import numpy as np
import pytest
from mcap.reader import make_reader
from scan_helpers import CAMERA, plan

from capture.recording import (
    DEPTH_TOPIC,
    DOCUMENTS_TOPIC,
    RecordingError,
    next_segment,
    read_recording,
)
from capture.runner import ScanRunner


def record(tmp_path, n_views=5, name="scan"):
    station = f"rec-{uuid.uuid4().hex[:8]}"
    runner = ScanRunner(plan(n_views), camera_url=f"{CAMERA}&station={station}",
                        turntable_url=f"sim://turntable?instant=1&station={station}",
                        out_dir=tmp_path / name)
    assert runner.start().wait(timeout=60) == "done"
    return runner


def test_round_trip_is_lossless_and_opens_with_the_seeking_reader(tmp_path):
    runner = record(tmp_path)
    recording = read_recording(tmp_path / "scan" / "recording.mcap")
    assert recording.complete and recording.plan == runner.plan
    np.testing.assert_array_equal(recording.calibration.camera_to_table,
                                  runner.station.calibration.camera_to_table)
    assert recording.station["camera"].startswith("sim://camera")
    live = [d for d in runner.documents if d.kind == "view"]
    assert len(recording.views) == len(live) == 5
    for got, sent in zip(recording.views, live, strict=True):
        assert (got.index, got.angle_deg, got.timestamps) == (sent.index, sent.angle_deg,
                                                              sent.timestamps)
        for a, b in zip(got.frames, sent.frames, strict=True):
            assert a.dtype == np.uint16
            np.testing.assert_array_equal(a, b)
    assert [d["kind"] for d in recording.documents] == [d.kind for d in runner.documents]
    with open(tmp_path / "scan" / "recording.mcap", "rb") as handle:  # Foxglove's way in
        reader = make_reader(handle)
        summary = reader.get_summary()
        topics = {c.topic for c in summary.channels.values()}
        assert topics == {DOCUMENTS_TOPIC, DEPTH_TOPIC}
        assert summary.statistics.message_count == len(runner.documents) + 5 * 2
        (meta,) = list(reader.iter_metadata())
        assert meta.name == "scanstation" and "plan" in meta.metadata


def test_every_truncation_keeps_each_view_completed_before_it(tmp_path):
    record(tmp_path, n_views=4)
    path = tmp_path / "scan" / "recording.mcap"
    data = path.read_bytes()
    full = read_recording(path)
    ends = []  # file size when each view's chunk was complete: the smallest prefix holding it
    torn = tmp_path / "torn" / "recording.mcap"
    torn.parent.mkdir()
    sizes = sorted(random.Random(0).sample(range(len(data)), 80)) + [len(data) - 1]
    for size in sizes:
        torn.write_bytes(data[:size])
        try:
            got = read_recording(torn)
        except RecordingError as exc:  # cut inside the header: written before anything moves
            assert "not a ScanStation recording" in str(exc) and not ends
            continue
        assert not got.complete
        assert [v.index for v in got.views] == list(range(len(got.views)))
        for v, w in zip(got.views, full.views, strict=False):
            np.testing.assert_array_equal(v.frames[0], w.frames[0])
        ends.append(len(got.views))
    assert ends == sorted(ends) and ends[-1] == 4 and ends[0] == 0 and len(ends) > 60


def test_a_damaged_byte_keeps_each_view_completed_before_it(tmp_path):
    record(tmp_path, n_views=4)
    path = tmp_path / "scan" / "recording.mcap"
    data = path.read_bytes()
    full = read_recording(path)
    damaged = tmp_path / "damaged" / "recording.mcap"
    damaged.parent.mkdir()
    kept = []
    for at in sorted(random.Random(1).sample(range(len(data) // 4, len(data) - 64), 24)):
        flipped = bytearray(data)
        flipped[at] ^= 0xFF  # a bad sector: in a chunk's zstd data, its CRC, or a header
        damaged.write_bytes(bytes(flipped))
        got = read_recording(damaged)
        torn = read_recording(_cut(damaged, data[:at]))  # what a cut there keeps
        assert len(got.views) >= len(torn.views), at
        for v, w in zip(got.views, full.views, strict=False):
            np.testing.assert_array_equal(v.frames[0], w.frames[0])
        kept.append(len(got.views))
    assert min(kept) < 4 and 3 in kept  # (a flip off the views' data loses none)


def _cut(path, data):
    cut = path.with_name("cut") / "recording.mcap"
    cut.parent.mkdir(exist_ok=True)
    cut.write_bytes(data)
    return cut


def test_unreadable_inputs_name_the_cause(tmp_path):
    with pytest.raises(RecordingError, match="no such recording"):
        read_recording(tmp_path / "missing.mcap")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="no recording.mcap in this directory"):
        read_recording(tmp_path / "empty")
    (tmp_path / "junk.mcap").write_bytes(b"this is not mcap at all")
    with pytest.raises(RecordingError, match="not a ScanStation recording"):
        read_recording(tmp_path / "junk.mcap")
    assert next_segment(tmp_path / "nowhere")[0] == 1


CHILD = """
import sys
from capture.plan import ScanPlan
from capture.runner import ScanRunner
plan = ScanPlan.turn(24, frames_per_view=2, settle_s=0.0, reconstruction=None)
runner = ScanRunner(plan, camera_url=sys.argv[2], turntable_url=sys.argv[3], out_dir=sys.argv[1])

def report(document):
    if document.kind == "view":  # the recorder ran (and synced) before any other subscriber
        print(f"view {document.index}", flush=True)

runner.subscribe(report)
runner.start().wait()
"""


def test_sigkill_at_random_moments_loses_no_completed_view(tmp_path):
    rng = random.Random(4)
    env = {**os.environ, "PYTHONPATH": os.getcwd()}
    for trial in range(4):
        out = tmp_path / f"killed-{trial}"
        station = f"kill-{trial}"
        camera = f"sim://camera?width=320&height=200&station={station}"
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD, str(out), camera,
             f"sim://turntable?instant=1&station={station}"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
        completed = []
        kill_after = rng.randrange(1, 20)
        try:
            for line in child.stdout:
                completed.append(int(line.split()[1]))
                if len(completed) >= kill_after:
                    time.sleep(rng.uniform(0.0, 0.05))  # land anywhere in the next view
                    break
        finally:
            child.send_signal(signal.SIGKILL)
            child.wait()
        for line in child.stdout:  # views reported in the instant before the kill
            completed.append(int(line.split()[1]))
        assert child.returncode == -signal.SIGKILL
        recording = read_recording(out)
        recovered = [v.index for v in recording.views]
        assert not recording.complete
        assert recovered[: len(completed)] == completed, (trial, kill_after)
        assert recovered == list(range(len(recovered)))
        assert all(len(v.frames) == 2 and v.frames[0].shape == (200, 320)
                   for v in recording.views)
