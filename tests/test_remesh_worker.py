"""Half an atlas's charts re-meshed in a worker process beside this one: the same meshes and
warnings as in this process alone, and a worker that dies leaves its charts to this one
(reconstruct.remesh_worker)."""

import logging
import os
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest
from surface_checks import sphere_cloud

from reconstruct import atlas_remesh, remesh_worker
from reconstruct.atlas import AtlasReconstructor
from reconstruct.errors import InvalidInputError


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    atlas = AtlasReconstructor(chart_size=400, random_state=0).fit(sphere_cloud(2000))
    return atlas.save(tmp_path_factory.mktemp("worker") / "sphere.npz")


@pytest.fixture
def worker(monkeypatch):
    monkeypatch.setattr(remesh_worker, "_worker", None)  # this test's own
    monkeypatch.setattr(atlas_remesh, "MIN_CHARTS", 2)
    worker = remesh_worker.shared_worker()
    yield worker
    worker.close()


def held(worker, atlas, timeout=120.0):
    stop = time.monotonic() + timeout
    while not worker.holds(atlas):
        assert time.monotonic() < stop, "the worker did not take up the charts"
        time.sleep(0.05)


def remeshed(atlas, change):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = atlas.remesh(**change)
    return mesh, sorted(str(w.message) for w in caught)


def test_the_worker_meshes_half_the_charts_as_this_process_would(saved, worker):
    beside, alone = AtlasReconstructor.load(saved), AtlasReconstructor.load(saved)
    alone.n_jobs = 1  # no worker
    assert len(beside.charts_) >= 4
    for atlas in (beside, alone):
        atlas.remesh(lam=2.0)
    assert beside.remesh_counts_["charts in the worker"] == 0  # sent after it
    sent_through = worker._file
    held(worker, beside)
    assert not os.path.exists(sent_through) and not os.path.exists(worker._shared)
    for change in ({"lam": 0.7}, {"depth": 3}, {"lam": 0.05}, {"lam": 3.0, "depth": 2}):
        mesh, said = remeshed(beside, change)
        expected, expected_said = remeshed(alone, change)
        np.testing.assert_array_equal(mesh.vertices, expected.vertices)
        np.testing.assert_array_equal(mesh.faces, expected.faces)
        assert said == expected_said, change  # the worker's charts' warnings passed on
        assert 0 < beside.remesh_counts_["charts in the worker"] < len(beside.charts_)
        assert alone.remesh_counts_["charts in the worker"] == 0
        for mine, theirs in zip(beside.charts_, alone.charts_, strict=True):
            assert (mine.lam, mine.depth) == (theirs.lam, theirs.depth)
            assert ("mesh_" in vars(mine)) == ("mesh_" in vars(theirs))
            np.testing.assert_array_equal(mine.outline_, theirs.outline_)


def test_a_worker_that_dies_leaves_its_charts_to_this_process(saved, worker, caplog):
    beside, alone = AtlasReconstructor.load(saved), AtlasReconstructor.load(saved)
    alone.n_jobs = 1
    for atlas in (beside, alone):
        atlas.remesh(lam=2.0)
    held(worker, beside)
    os.kill(worker._process.pid, signal.SIGKILL)
    with caplog.at_level(logging.WARNING, logger="reconstruct.remesh_worker"):
        mesh, _ = remeshed(beside, {"lam": 0.7})
    assert "the chart re-meshing worker failed" in caplog.text
    assert worker.failed and beside.remesh_counts_["charts in the worker"] == 0
    expected, _ = remeshed(alone, {"lam": 0.7})
    np.testing.assert_array_equal(mesh.vertices, expected.vertices)
    mesh, _ = remeshed(beside, {"lam": 3.0})  # and goes on without one
    expected, _ = remeshed(alone, {"lam": 3.0})
    np.testing.assert_array_equal(mesh.vertices, expected.vertices)
    assert worker._process is None


def test_an_atlas_fitted_without_workers_keeps_its_charts_here(saved, worker):
    alone = AtlasReconstructor.load(saved)
    alone.n_jobs = 1
    remeshed(alone, {"lam": 2.0})
    remeshed(alone, {"lam": 0.7})
    assert not worker.sent(alone) and worker._process is None


def test_a_refused_remesh_leaves_the_worker_in_step(saved, worker):
    """A re-mesh that raises in this process's half leaves the worker's answer unread: the
    next re-mesh reads it first, not in place of its own."""
    beside, alone = AtlasReconstructor.load(saved), AtlasReconstructor.load(saved)
    alone.n_jobs = 1
    for atlas in (beside, alone):
        atlas.remesh(lam=2.0)
    held(worker, beside)
    for atlas in (beside, alone):
        with pytest.raises(InvalidInputError):
            atlas.remesh(lam=-1.0)
    mesh, _ = remeshed(beside, {"lam": 0.7})
    expected, _ = remeshed(alone, {"lam": 0.7})
    np.testing.assert_array_equal(mesh.vertices, expected.vertices)
    assert beside.remesh_counts_["charts in the worker"] > 0


def test_a_forked_process_makes_its_own_worker(worker):
    """A process forked after a re-mesh must not talk through its parent's pipe."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: a worker of its own
        os.write(write, b"1" if remesh_worker.shared_worker() is not worker else b"0")
        os._exit(0)
    os.waitpid(pid, 0)
    answer = os.read(read, 1)
    os.close(read)
    os.close(write)
    assert answer == b"1"
    assert remesh_worker.shared_worker() is worker


def test_a_process_that_exits_after_one_remesh_leaves_no_file(saved):
    """Its charts were sent to a worker still starting: the files go with the process."""
    code = (
        "import sys\n"
        "from reconstruct import atlas_remesh, remesh_worker\n"
        "from reconstruct.atlas import AtlasReconstructor\n"
        "atlas_remesh.MIN_CHARTS = 2\n"
        f"AtlasReconstructor.load({str(saved)!r}).remesh(lam=2.0)\n"
        "worker = remesh_worker.shared_worker()\n"
        "print(worker._file, worker._shared)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    paths = run.stdout.split()
    assert len(paths) == 2 and not any(os.path.exists(path) for path in paths), run.stdout


def test_the_worker_takes_up_charts_prepared_and_one_it_cannot_prepare_as_it_is(
        saved, tmp_path, monkeypatch):
    import pickle

    from reconstruct.pipeline import SurfaceReconstructor

    atlas = AtlasReconstructor.load(saved)
    charts = {i: chart.state() for i, chart in enumerate(atlas.charts_[:2])}
    path = tmp_path / "charts"
    path.write_bytes(pickle.dumps({"key": 1, "owners": None, "reach": 1.0, "charts": charts}))
    prepare = SurfaceReconstructor.prepare_remeshing

    def failing_once(chart):
        if not prepared:
            prepared.append(chart)
            raise RuntimeError("a chart that cannot be prepared")
        prepare(chart)
    prepared = []
    monkeypatch.setattr(SurfaceReconstructor, "prepare_remeshing", failing_once)
    held = remesh_worker._take(str(path))
    assert not path.exists() and sorted(held["charts"]) == [0, 1]
    assert "spline" not in held["charts"][0]._boundary_cache  # as loaded
    assert "spline" in held["charts"][1]._boundary_cache  # its depths' inputs, taken
    for index, chart in held["charts"].items():  # both re-mesh as the atlas's own
        mine = atlas.charts_[index]
        chart.remesh(lam=2.0)
        mine.remesh(lam=2.0)
        assert np.array_equal(chart.mesh_.vertices, mine.mesh_.vertices)
