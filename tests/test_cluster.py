"""Fits and batch re-processing on a real Dask cluster (`distributed.LocalCluster`, 2 worker
processes started here): the meshes are the live scans' bit for bit, a corrupt recording fails
alone with its cause, a second run skips everything, a worker killed mid-run changes nothing, and
an unreachable scheduler is a one-line error."""

import contextlib
import io
import os
import signal
import threading
import time

import pytest
from scan_helpers import record

from capture.cli import main

distributed = pytest.importorskip("distributed")

OBJECTS = {"box": ("box", 0), "bust": ("bust", 0), "box-noisier": ("box", 1)}


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """A collection folder of three live scans (recording.mcap + their meshes), and a corrupt
    recording beside it."""
    root = tmp_path_factory.mktemp("collection")
    for name, (obj, seed) in OBJECTS.items():
        record(root / "scans" / name, obj, seed)
    corrupt = root / "corrupt" / "recording.mcap"
    corrupt.parent.mkdir()
    corrupt.write_bytes((root / "scans" / "box" / "recording.mcap").read_bytes()[:3000])
    return root


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as local:
        yield local


@pytest.fixture(scope="module")
def first_run(recordings, cluster, tmp_path_factory):
    """The first re-processing of the scans and the corrupt recording: (its folder, the cluster
    arguments, the exit code, the table printed). Run here, not by the test that checks it: a
    test that needs it done may run first, or in another xdist worker."""
    out = tmp_path_factory.mktemp("reprocessed")
    cluster_args = ["--cluster", cluster.scheduler_address]
    table = io.StringIO()
    with contextlib.redirect_stdout(table):
        code = main(["reprocess", str(recordings / "scans"), str(recordings / "corrupt"),
                     "-o", str(out), *cluster_args])
    return out, cluster_args, code, table.getvalue()


def _mesh_bytes(folder):
    return (folder / "mesh.ply").read_bytes()


def test_reprocess_on_a_cluster_gives_the_live_meshes_and_a_corrupt_one_fails_alone(
        recordings, first_run):
    out, _, code, table = first_run
    assert code == 1  # one failed
    for name in OBJECTS:
        assert _mesh_bytes(out / name) == _mesh_bytes(recordings / "scans" / name)
        for produced in ("cloud.ply", "scan.json", "reprocess.json", "engine/engine.json"):
            assert (out / name / produced).is_file()
        assert f"\n{name} " in table and "ok" in table.split(f"\n{name} ")[1].split("\n")[0]
    failed = [line for line in table.splitlines() if line.startswith("corrupt ")]
    assert len(failed) == 1 and "failed" in failed[0]
    assert "RecordingError" in failed[0] and "corrupt/recording.mcap" in failed[0]
    assert not (out / "corrupt").exists()
    assert "4 recordings" in table and "3 ok, 0 skipped, 1 failed" in table
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no partial folder left


def test_a_second_run_skips_everything_up_to_date(recordings, first_run, capsys):
    out, cluster, _, _ = first_run
    before = {name: (out / name / "mesh.ply").stat().st_mtime_ns for name in OBJECTS}
    assert main(["reprocess", str(recordings / "scans"), "-o", str(out), *cluster]) == 0
    table = capsys.readouterr().out
    assert "3 recordings" in table and "0 ok, 3 skipped, 0 failed" in table
    assert before == {name: (out / name / "mesh.ply").stat().st_mtime_ns for name in OBJECTS}
    # another λ is another result: not skipped
    assert main(["reprocess", str(recordings / "scans" / "bust"), "-o", str(out), "--lam", "3",
                 *cluster]) == 0
    assert "1 ok, 0 skipped" in capsys.readouterr().out
    assert _mesh_bytes(out / "bust") != _mesh_bytes(recordings / "scans" / "bust")


def test_replay_with_cluster_fits_on_the_workers_and_gives_the_live_mesh(
        recordings, cluster, tmp_path, capsys):
    source = recordings / "scans" / "bust"
    assert main(["replay", str(source), "-o", str(tmp_path), "--cluster",
                 cluster.scheduler_address]) == 0
    assert _mesh_bytes(tmp_path) == _mesh_bytes(source)


def test_a_worker_killed_mid_run_is_retried_and_the_meshes_are_identical(
        recordings, cluster, tmp_path, capsys):
    from capture.executors import make_executor
    from capture.reprocess import Reprocessor, find_recordings

    executor = make_executor(cluster.scheduler_address)
    client = executor.client
    killed = []

    def kill_a_busy_worker():
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not killed:
            busy = [w for w, keys in client.processing().items() if keys]
            if busy:
                time.sleep(1.0)  # inside the fit
                pids = client.run(os.getpid, workers=busy[:1])
                for pid in pids.values():
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
            time.sleep(0.05)

    names = ["box", "bust"]
    killer = threading.Thread(target=kill_a_busy_worker)
    killer.start()
    try:
        outcomes = Reprocessor(tmp_path, executor=executor).run(
            find_recordings([recordings / "scans" / name for name in names]))
    finally:
        killer.join()
        executor.shutdown()
    assert killed, "no worker was killed: the test did not test anything"
    assert [o.status for o in outcomes] == ["ok"] * 2, [o.cause for o in outcomes]
    for name in names:
        assert _mesh_bytes(tmp_path / name) == _mesh_bytes(recordings / "scans" / name)
    client_after = distributed.Client(cluster.scheduler_address, set_as_default=False)
    try:
        client_after.wait_for_workers(2, timeout=60)  # the nanny restarted it
    finally:
        client_after.close()


def test_an_unreachable_scheduler_is_a_one_line_error(recordings, tmp_path, capsys,
                                                        monkeypatch):
    monkeypatch.setattr("capture.executors.CONNECT_TIMEOUT_S", 1.0)
    source = str(recordings / "scans" / "box")
    assert main(["reprocess", source, "-o", str(tmp_path), "--cluster",
                 "tcp://127.0.0.1:9"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("scanstation: error: Dask scheduler tcp://127.0.0.1:9 "
                              "unreachable: "), err
    assert main(["replay", source, "-o", str(tmp_path), "--cluster",
                 "tcp://no-such-host.invalid:8786"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "cannot resolve no-such-host.invalid" in err
    assert not list(tmp_path.iterdir())  # nothing written


def test_daemon_scans_fit_on_the_cluster_given_to_serve(recordings, cluster, tmp_path):
    import shutil

    from capture.daemon.isolation import RunSpec, build_runner
    from capture.executors import ClusterExecutor

    scan = shutil.copytree(recordings / "scans" / "box", tmp_path / "box")
    (scan / "mesh.ply").unlink()
    runner = build_runner(RunSpec(None, scan, replay=True, cluster=cluster.scheduler_address))
    assert isinstance(runner.executor, ClusterExecutor)
    try:
        assert runner.start().wait(timeout=300) == "done", runner.reason
    finally:
        runner.executor.shutdown()
    assert _mesh_bytes(scan) == _mesh_bytes(recordings / "scans" / "box")


def test_serve_with_an_unreachable_cluster_stops_with_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("capture.executors.CONNECT_TIMEOUT_S", 1.0)
    assert main(["serve", "--state-dir", str(tmp_path), "--port", "0", "--cluster",
                 "tcp://127.0.0.1:9"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("scanstation: error: Dask scheduler tcp://127.0.0.1:9 unreachable")
