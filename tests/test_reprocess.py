"""`scanstation reprocess` without a cluster: finding recordings, the fingerprint, atomic outputs,
and the default path (local processes) that never imports Dask."""

import json
import os
import subprocess
import sys

import pytest
from scan_helpers import record

from capture.reprocess import (
    STAMP,
    TEMP_PREFIX,
    Job,
    ReprocessError,
    Reprocessor,
    find_recordings,
    replay_folder_prefix,
    sweep_stale_folders,
    up_to_date,
    write_outputs,
)


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scans") / "bust"
    record(folder, "bust")
    return folder


def test_find_recordings_walks_folders_and_names_outputs(tmp_path):
    for folder in ("a/scan1", "a/scan2", "b/deep/scan3"):
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "recording.mcap").write_bytes(b"x")
    (tmp_path / "a" / "scan2" / "recording-2.mcap").write_bytes(b"y")
    (tmp_path / "lone.mcap").write_bytes(b"z")
    jobs = find_recordings([tmp_path / "a", tmp_path / "b", tmp_path / "lone.mcap"])
    assert [j.name for j in jobs] == ["scan1", "scan2", "scan3", "lone"]
    assert [p.name for p in jobs[1].segments] == ["recording.mcap", "recording-2.mcap"]
    assert find_recordings([tmp_path / "a" / "scan1" / "recording.mcap"])[0].name == "scan1"
    with pytest.raises(ReprocessError, match="no such file or folder"):
        find_recordings([tmp_path / "missing"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ReprocessError, match="no recording"):
        find_recordings([tmp_path / "empty"])
    (tmp_path / "c" / "scan1").mkdir(parents=True)
    (tmp_path / "c" / "scan1" / "recording.mcap").write_bytes(b"x")
    with pytest.raises(ReprocessError, match="would both write OUT/scan1"):
        find_recordings([tmp_path / "a", tmp_path / "c"])
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ReprocessError, match="not a recording"):
        find_recordings([tmp_path / "notes.txt"])


def test_fingerprint_follows_content_and_parameters(tmp_path):
    source = tmp_path / "in" / "scan"
    source.mkdir(parents=True)
    (source / "recording.mcap").write_bytes(b"recorded bytes")
    (job,) = find_recordings([source])
    target = tmp_path / "out" / job.name
    from capture.reprocess import fingerprint

    files = {"mesh.ply": b"m", "cloud.ply": b"c", "scan.json": b"{}", "engine/engine.json": b"{}"}
    write_outputs(target, files, fingerprint(job, {"lam": 2.0}))
    assert up_to_date(target, job, {"lam": 2.0})
    assert not up_to_date(target, job, {"lam": 3.0})
    assert not up_to_date(target, job, {})
    os.utime(source / "recording.mcap", ns=(1, 1))  # touched, same bytes: still up to date
    assert up_to_date(target, job, {"lam": 2.0})
    (source / "recording.mcap").write_bytes(b"recorded bytez")  # same size, new content
    assert not up_to_date(target, job, {"lam": 2.0})
    # a rewrite swaps the whole folder: no stale file from the previous outputs survives
    write_outputs(target, {"mesh.ply": b"new"}, {"format": "x"})
    assert sorted(p.name for p in target.iterdir()) == ["mesh.ply", STAMP]
    assert [p.name for p in target.parent.iterdir()] == [job.name]


@pytest.mark.skipif(os.name != "posix", reason="a folder's process is named by its pid")
def test_a_killed_replay_s_temporary_folder_is_removed_by_the_next(tmp_path):
    # a worker killed mid-replay (SIGKILL: CI's killed-worker test) left its copy of the
    # recording in the temporary folder, one per kill
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    stale = tmp_path / f"{replay_folder_prefix(gone.pid)}abc"
    (stale / "in").mkdir(parents=True)
    (stale / "in" / "recording.mcap").write_bytes(b"x" * 100)
    live = tmp_path / f"{replay_folder_prefix()}def"  # a replay under way: kept
    unnamed = tmp_path / f"{TEMP_PREFIX}_k6ljt5o"  # no process named: not ours to judge
    elsewhere = tmp_path / f"{TEMP_PREFIX}another-host-{gone.pid}-x"  # another host's
    other = tmp_path / f"other-{gone.pid}-x"
    for folder in (live, unnamed, elsewhere, other):
        folder.mkdir()
    assert sweep_stale_folders(tmp_path) == 1
    assert not stale.exists()
    assert all(f.is_dir() for f in (live, unnamed, elsewhere, other))
    assert sweep_stale_folders(tmp_path) == 0


def test_a_missing_segment_fails_that_recording_only(tmp_path):
    gone = Job("gone", (tmp_path / "gone" / "recording.mcap",))
    outcomes = Reprocessor(tmp_path / "out").run([gone])
    assert outcomes[0].status == "failed" and "No such file" in outcomes[0].cause


def test_a_lone_recording_file_is_reprocessed_whatever_its_name(scan, tmp_path):
    import shutil

    lone = tmp_path / "lone" / "scan-0042.mcap"
    lone.parent.mkdir()
    shutil.copy(scan / "recording.mcap", lone)
    (job,) = find_recordings([lone])
    (outcome,) = Reprocessor(tmp_path / "out").run([job])
    assert outcome.status == "ok", outcome.cause
    assert (tmp_path / "out" / job.name / "mesh.ply").read_bytes() == \
        (scan / "mesh.ply").read_bytes()


def test_a_missing_path_is_one_expected_line(tmp_path, capsys):
    from capture.cli import main

    assert main(["reprocess", str(tmp_path / "nope"), "-o", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("scanstation: error: ") and "unexpected" not in err
    assert "no such file or folder" in err and len(err.splitlines()) == 1


def test_default_path_runs_on_local_processes_without_importing_dask(scan, tmp_path):
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(b"\x89MCAP0\r\n" + os.urandom(200))
    out = tmp_path / "out"
    script = (
        "import sys, json\n"
        "from capture.cli import main\n"
        f"code = main(['reprocess', {str(scan)!r}, {str(corrupt)!r}, '-o', {str(out)!r},"
        " '--workers', '2'])\n"
        f"code2 = main(['replay', {str(scan)!r}, '-o', {str(tmp_path / 'replay')!r},"
        " '--workers', '1'])\n"
        "print(json.dumps([code, code2, sorted(m for m in sys.modules"
        " if m.split('.')[0] in ('dask', 'distributed'))]))\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=600, cwd=os.getcwd())
    code, code2, dask_modules = json.loads(run.stdout.strip().splitlines()[-1])
    assert (code, code2) == (1, 0), run.stderr
    assert dask_modules == []
    assert "corrupt" in run.stdout and "failed" in run.stdout
    live = (scan / "mesh.ply").read_bytes()
    assert (out / "bust" / "mesh.ply").read_bytes() == live
    assert (tmp_path / "replay" / "mesh.ply").read_bytes() == live
    stamp = json.loads((out / "bust" / STAMP).read_text())
    assert stamp["params"] == {} and stamp["segments"][0]["name"] == "recording.mcap"
    report = json.loads((out / "bust" / "scan.json").read_text())
    assert str(out / "bust") in report["files"]["mesh"]  # the final path, not the worker's
