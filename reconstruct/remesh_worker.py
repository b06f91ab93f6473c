"""A second process that re-meshes an atlas's charts beside this one (`reconstruct.atlas_remesh`).

A chart's re-mesh (`SurfaceReconstructor.remesh_unless`: its spline, outline, lattice, the test
that its part of the join is unchanged, and maybe its mesh) is mostly Python and small numpy
calls, so threads in one process take turns on one core (hook 22k, 92 charts: 349 ms in two
threads, 317 ms in one). A worker process holding copies of the charts meshes them beside this
one: this process takes them from the first, the worker from the last, each publishing how far
it has come in a small shared file, until they meet (a chart both took at the meeting point is
this process's); the charts' costs differ too much for a fixed half each (figurine 22k: the
parent waited 20-80 ms for the worker's every other chart).

The worker is sent the charts' saved state (`SurfaceReconstructor.state`: a loaded chart
re-meshes as its original) at the end of a re-mesh of an atlas it does not hold, through a
file, and takes them up in the background (about 1.5 s the first time, most of it imports);
until then, in a daemonic process (a Dask worker, which may start none) or for an atlas with
``n_jobs=1``, this process meshes every chart. Each re-mesh sends every chart's mesh
parameters with the change, so a copy meshes as its original would, and takes back what the
re-mesh set on the charts the worker took, with their parts of the join. The worker is
daemonic: an exiting process stops it rather than waiting for it. One that fails (killed, a
broken pipe) is said once in the log, its charts are meshed here, and no other is started.
"""

from __future__ import annotations

import logging
import mmap
import os
import pickle
import tempfile
import threading
import warnings
from multiprocessing.util import Finalize

import numpy as np
import trimesh

from .chart_logs import chart_steps
from .chart_parts import ChartPart, parts_of, unchanged
from .errors import DegenerateCloudError, FitError, ReconstructionWarning
from .io import one_line
from .join import owned

log = logging.getLogger(__name__)

#: Charts below which an atlas is re-meshed in this process alone (the worker's round trip and
#: the pickling of its results outweigh a share of a few charts' 3-8 ms).
MIN_CHARTS = 8
#: The worker process's name.
NAME = "chart re-meshing worker"
#: Seconds this process waits for an answer of the worker before taking it for hung (and
#: meshing its charts here).
WAIT = 60.0
#: What `SurfaceReconstructor.remesh_unless` sets on a chart, taken back from the worker (with,
#: when it meshed, the mesh's vertices and faces); the first three also when it did not.
_SET = ("boundary_points_", "spline_", "outline_", "vertices_2d_", "_outline_lattice",
        "timings_")


def remesh_chart(chart, index: int, part: ChartPart | None, params: dict, owners,
                 reach: float):
    """Re-mesh ``chart`` (the atlas's chart ``index``) with ``params`` unless its ``part`` of
    the join cannot change (`chart_parts.unchanged`; ``owners``: the atlas's labels and tree of
    the charted points, ``reach``: how far from them a vertex is the chart's); returns whether
    it was meshed, or the error of a chart whose boundary cannot take them (a small chart's
    spline that a large λ collapses, too few points at a depth: the chart keeps its parameters
    and mesh)."""
    test = None
    if part is not None and part.nodes is not None:  # else never unchanged: nothing to test
        labels, tree = owners

        def mine(positions):
            return owned([positions], labels, tree, reach, charts=[index])[0]

        def test(outline, spacing, grid):
            return unchanged(part, outline, spacing, chart.surface_map_, mine, grid)
    try:
        with chart_steps():
            return chart.remesh_unless(test, **params)
    except (FitError, DegenerateCloudError) as exc:
        return exc


class ChartWorker:
    """The worker process (one per process: `shared_worker`): `send` it an atlas's charts,
    `holds` says whether it has taken them up, `submit` and `results` re-mesh the charts it
    takes (`take`: this process from the first, the worker from the last)."""

    def __init__(self):
        self._process = self._pipe = None
        self._sent = None  # (the charts sent, each with its map; the owners; the key)
        self._taking = None  # the key of charts sent and not yet taken up
        self._held = None  # the key of the charts it holds
        self._file = self._shared = self._frontier = None
        self._unread = False  # an answer to `submit` not taken by `results`
        self._key = 0
        self._lock = threading.Lock()
        self.failed = False
        self.pid = os.getpid()  # the process it serves
        self._finalizing = False

    def take(self, index: int) -> bool:
        """Take chart ``index`` (ascending from 0) in this process unless the worker, which
        takes them from the last, has: then False, and this process stops."""
        if self._frontier[1] <= index:
            return False
        self._frontier[0] = index + 1
        return True

    def acquire(self) -> bool:
        """Take the worker for one re-mesh (False: another re-mesh has it, or it failed)."""
        return not self.failed and self._lock.acquire(blocking=False)

    def release(self) -> None:
        self._lock.release()

    def sent(self, atlas) -> bool:
        """Whether the worker was sent ``atlas``'s charts as they are fitted now."""
        if self._sent is None:
            return False
        charts, owners, _ = self._sent
        return (owners is atlas.__dict__.get("_owners") and len(charts) == len(atlas.charts_)
                and all(c is chart and m is chart.surface_map_
                        for (c, m), chart in zip(charts, atlas.charts_, strict=True)))

    def holds(self, atlas) -> bool:
        """Whether the worker has taken up ``atlas``'s charts as they are fitted now."""
        if not self.sent(atlas):
            return False
        if self._taking is not None:
            try:
                if not self._pipe.poll():
                    return False  # still taking them up
                self._held, self._taking = self._answer("taken"), None
            except Exception as exc:  # noqa: BLE001 - it died taking them up
                self._fail(exc)
                return False
        return self._held == self._sent[2]

    def send(self, atlas, reach: float) -> None:
        """Send the worker ``atlas``'s charts as they are now: their state in a
        file it reads while this process goes on. Not while it takes up others."""
        if self.failed or self._taking is not None:
            return
        try:
            if self._process is None:
                self._start()
            self._key += 1
            charts = {i: chart.state() for i, chart in enumerate(atlas.charts_)}
            handle, self._file = tempfile.mkstemp(prefix="scanstation-charts-")
            with os.fdopen(handle, "wb") as out:
                pickle.dump({"key": self._key, "owners": atlas._owners, "reach": reach,
                             "charts": charts}, out, protocol=pickle.HIGHEST_PROTOCOL)
            self._pipe.send(("take", self._file))
        except Exception as exc:  # noqa: BLE001 - no worker: this process meshes them all
            self._fail(exc)
            return
        self._taking = self._key
        self._sent = ([(c, c.surface_map_) for c in atlas.charts_], atlas._owners, self._key)

    def submit(self, atlas, parts, params: dict) -> bool:
        """Start the worker re-meshing its charts of ``atlas`` (which it `holds`) with
        ``params``; `results` gives them. False when it could not be asked."""
        jobs = [({name: getattr(chart, name) for name in _mesh_params()},
                 None if parts is None else _for_test(parts[i]))
                for i, chart in enumerate(atlas.charts_)]
        try:
            if self._unread:  # a re-mesh that raised here left the worker's answer
                self._answer("remeshed")
                self._unread = False
            self._frontier[:] = (0, len(jobs))  # none taken by either
            self._pipe.send(("remesh", (self._held, jobs, params)))
        except Exception as exc:  # noqa: BLE001 - it died
            self._fail(exc)
            return False
        self._unread = True
        return True

    def results(self) -> list | None:
        """The worker's results of `submit`: {chart index: (result, warnings said)} of the
        charts it took, the result the chart's error or (meshed, what the re-mesh set, the
        mesh's vertices and faces and its `ChartPart`); None (said once, in the log) when it
        failed."""
        try:
            answer = self._answer("remeshed")
        except Exception as exc:  # noqa: BLE001 - killed, a broken pipe: mesh here
            self._fail(exc)
            return None
        self._unread = False
        return answer

    def close(self) -> None:
        """Stop the worker process (a later `send` starts another)."""
        process, pipe, self._process, self._pipe = self._process, self._pipe, None, None
        self._sent = self._taking = self._held = None
        self._unread = False
        if pipe is not None:
            pipe.close()  # the worker reads the end of its pipe and returns
        if process is not None:
            process.join(timeout=5)
            if process.is_alive():
                process.kill()
                process.join(timeout=5)
        self._remove_files()
        self._file = self._shared = self._frontier = None

    def _remove_files(self) -> None:
        """Remove the files sent through that the worker has not (it removes the charts'
        once read, the frontiers' once mapped); also when this process exits
        (`multiprocessing.util.Finalize`: in a child process too, where atexit does not run)."""
        for path in (self._file, self._shared):
            if path is not None and os.path.exists(path):
                os.remove(path)

    def _start(self) -> None:
        # loky's spawning: a fresh interpreter that, unlike multiprocessing's spawn, does not
        # run the caller's main script again (a script without a __main__ guard would re-mesh
        # in its worker, and so on)
        from joblib.externals.loky.backend import get_context

        context = get_context("loky")
        # the frontiers (the next chart this process would take, the last the worker took),
        # two int64 in a file both map; a plain store each, read by the other (a stale read
        # makes both take the chart where they meet, never neither)
        handle, self._shared = tempfile.mkstemp(prefix="scanstation-frontiers-",
                                                dir="/dev/shm" if os.path.isdir("/dev/shm")
                                                else None)
        os.write(handle, bytes(16))
        self._frontier = _frontier(handle)
        os.close(handle)
        if not self._finalizing:
            Finalize(None, self._remove_files, exitpriority=10)
            self._finalizing = True
        self._pipe, theirs = context.Pipe()
        process = context.Process(target=_serve, args=(theirs, self._shared), name=NAME,
                                  daemon=True)
        process.start()
        self._process = process
        theirs.close()

    def _answer(self, kind: str):
        """The worker's next answer, which must be of ``kind`` (raises otherwise, or when
        it died, or when none came within `WAIT` seconds)."""
        waited = 0.0
        while not self._pipe.poll(0.5):
            waited += 0.5
            if not self._process.is_alive() or waited >= WAIT:
                raise RuntimeError(f"the worker {'died' if waited < WAIT else 'hangs'} "
                                   f"(exit code {self._process.exitcode})")
        answer, payload = self._pipe.recv()
        if answer != kind:
            raise RuntimeError(f"the worker answered {answer}: {payload}")
        return payload

    def _fail(self, exc: BaseException) -> None:
        if not self.failed:
            log.warning("the chart re-meshing worker failed (%s); re-meshing every chart in "
                        "this process", one_line(exc))
        self.failed = True
        self.close()


_worker: ChartWorker | None = None
_worker_lock = threading.Lock()


def shared_worker() -> ChartWorker:
    """The process's `ChartWorker` (made on first use; its process on its first `send`). A
    process forked from one that had a worker makes its own (the pipe is its parent's)."""
    global _worker
    with _worker_lock:
        if _worker is None or _worker.pid != os.getpid():
            _worker = ChartWorker()
        return _worker


def apply(chart, params: dict, result) -> bool | Exception:
    """Set on ``chart`` what the worker's re-mesh with ``params`` set on its copy (``result``,
    as `ChartWorker.results` gives it for the chart); returns whether it was meshed, or the
    chart's error."""
    if isinstance(result, Exception):
        return result
    meshed, fields, arrays = result
    vars(chart).update({k: v for k, v in params.items() if v is not None})
    for name in ("mesh_", "vertices_2d_"):
        vars(chart).pop(name, None)
    vars(chart).update(fields)
    if meshed:
        chart.mesh_ = trimesh.Trimesh(*arrays[:2], process=False)
    return meshed


def part_given(result) -> ChartPart | None:
    """The chart's part of the join that the worker took with ``result`` (its mesh's), if
    it meshed."""
    return None if isinstance(result, Exception) or not result[0] else result[2][2]


def _mesh_params() -> tuple:
    from .pipeline import _MESH_PARAMS

    return _MESH_PARAMS


def _for_test(part: ChartPart | None) -> ChartPart | None:
    """What `chart_parts.unchanged` needs of ``part`` (not its samples and normals)."""
    if part is None or part.nodes is None:
        return None
    empty = np.zeros((0, 3))
    return ChartPart(empty, empty, part.kept[:0], part.nodes, part.first, part.deep)


def _frontier(handle: int) -> np.ndarray:
    """(2,) int64 over the shared file open as ``handle``: the next chart the parent would
    take, the last chart the worker took."""
    return np.frombuffer(mmap.mmap(handle, 16), np.int64)


def _serve(pipe, shared: str) -> None:
    """The worker: answer the requests on ``pipe`` in order until it is closed; ``shared``
    the file of the frontiers."""
    from .threads import single_threaded

    handle = os.open(shared, os.O_RDWR)
    frontier = _frontier(handle)
    os.close(handle)
    os.remove(shared)  # both have it mapped: no file left behind
    held: dict = {}
    with single_threaded():  # one core here, the other the parent's
        while True:
            try:
                kind, payload = pipe.recv()
            except (EOFError, OSError):
                return
            try:
                if kind == "take":
                    held = _take(payload)
                    answer = ("taken", held["key"])
                else:
                    answer = ("remeshed", _remesh_held(held, frontier, *payload))
                pipe.send(answer)
            except Exception as exc:  # noqa: BLE001 - said to the parent, which meshes here
                pipe.send(("failed", one_line(exc)))


def _take(path: str) -> dict:
    """The charts sent in the file at ``path`` (removed), rebuilt from their state."""
    from .pipeline import SurfaceReconstructor

    try:
        with open(path, "rb") as stream:
            sent = pickle.load(stream)
    finally:
        os.remove(path)
    charts = {}
    for i, (meta, arrays) in sent["charts"].items():
        charts[i] = SurfaceReconstructor.from_state(meta, arrays)
        charts[i].up = None  # (as `atlas_state` loads them)
        try:  # here, not in the worker's first re-mesh
            charts[i].prepare_remeshing()
        except Exception as exc:  # noqa: BLE001 - its re-mesh says so, as it would have
            log.debug("chart %d not prepared: %s", i, one_line(exc))
    return {**sent, "charts": charts}


def _remesh_held(held: dict, frontier: np.ndarray, key: int, jobs: list, params: dict) -> dict:
    """Re-mesh the ``held`` charts (sent under ``key``) from the last down, while the parent
    takes them from the first (``frontier``), each job (its mesh parameters in the parent,
    its part for the test) with ``params``; {index: (result, warnings said)} of those taken."""
    if held.get("key") != key:
        raise RuntimeError(f"it holds the charts sent as {held.get('key')}, not {key}")
    out = {}
    for index in range(len(jobs) - 1, -1, -1):
        if frontier[0] > index:  # the parent has taken it (and every one below)
            break
        frontier[1] = index
        current, part = jobs[index]
        chart = held["charts"][index]
        vars(chart).update(current)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ReconstructionWarning)
            try:
                meshed = remesh_chart(chart, index, part, params, held["owners"],
                                      held["reach"])
            except Exception as exc:  # noqa: BLE001 - raised in the parent, as it would be
                meshed = exc
        said = [str(w.message) for w in caught if issubclass(w.category, ReconstructionWarning)]
        if isinstance(meshed, Exception):
            out[index] = (meshed, said)
            continue
        names = _SET if meshed else _SET[:3]  # (an unmeshed copy's lattice is stale)
        fields = {name: vars(chart)[name] for name in names if name in vars(chart)}
        arrays = ((np.asarray(chart.mesh_.vertices), np.asarray(chart.mesh_.faces),
                   parts_of([chart], [index], held["owners"], held["reach"])[0])
                  if meshed else None)
        out[index] = ((meshed, fields, arrays), said)
    return out
