"""Re-meshing a fitted atlas with new boundary parameters (`AtlasReconstructor.remesh`): every
chart through its ONNX map, in threads, skipping those whose part of the join cannot change
(`reconstruct.chart_parts`), then the join again round the samples that moved; a chart whose
boundary cannot take the parameters keeps its own."""

from __future__ import annotations

import logging
import time
import warnings
from concurrent.futures import ThreadPoolExecutor

import trimesh

from .chart_fit import n_chart_workers
from .chart_parts import ChartPart
from .errors import DegenerateCloudError, FitError, ReconstructionError, ReconstructionWarning
from .io import one_line
from .join import kept_mesh
from .mesh_edges import topology
from .remesh_worker import (
    MIN_CHARTS,
    ChartWorker,
    apply,
    part_given,
    remesh_chart,
    shared_worker,
)

log = logging.getLogger(__name__)

#: Charts re-meshed at once, in threads (ONNX Runtime, GEOS and qhull release the GIL): torus
#: 22k, 37 charts, 2 cores: 266 -> 187 ms when measured; 280 -> 265 ms on a slower day
#: (2026-12-04), when most of a chart's 7.7 ms held the GIL (Python and small numpy calls).
REMESH_THREADS = 2


def remesh_atlas(atlas, params: dict) -> trimesh.Trimesh:
    """`AtlasReconstructor.remesh` of the fitted ``atlas`` with ``params`` (lam, depth, ...):
    sets its ``mesh_``, its ``lam`` and ``depth`` when given, ``timings_`` ("remesh charts",
    "join", "remesh") and ``remesh_counts_``, and returns the mesh. The charts are shared
    with a worker process once it holds them (`reconstruct.remesh_worker`), sent after the
    first re-mesh."""
    worker = _worker_for(atlas)
    try:
        mesh = _remesh(atlas, params, worker)
        # the atlas's parameters say what its charts were last meshed with (as a chart's do),
        # and what a state saved now re-meshes with
        vars(atlas).update({k: params[k] for k in ("lam", "depth") if params.get(k) is not None})
        if worker is not None and not worker.sent(atlas):  # for the next re-meshes
            worker.send(atlas, atlas.reach * atlas.decomposition_.spacing_)
        return mesh
    finally:
        if worker is not None:
            worker.release()


def _remesh(atlas, params: dict, worker: ChartWorker | None) -> trimesh.Trimesh:
    started = time.perf_counter()
    charts = atlas.charts_
    parts = atlas.__dict__.get("_parts")
    if parts is not None and len(parts) != len(charts):
        parts = None
    if parts is not None and "_owners" not in atlas.__dict__:  # loaded with its parts
        atlas._owners = atlas._chart_owners()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ReconstructionWarning)
        if worker is not None and worker.holds(atlas):  # (the join's parts taken, but for
            fresh, retake, in_worker = _remesh_beside(worker, atlas, parts, params)  # retake)
        else:
            fresh = retake = _remesh_here(atlas, range(len(charts)), parts, params)
            in_worker = 0
    said = [w for w in caught if issubclass(w.category, ReconstructionWarning)]
    if said:  # one line for the atlas, not one per chart
        warnings.warn(f"{len(said)} of {len(charts)} charts: {said[0].message}",
                      ReconstructionWarning, stacklevel=3)
    refused = [exc for exc in fresh if isinstance(exc, Exception)]
    if len(refused) == len(charts):
        raise refused[0]  # no chart took them: the atlas is as it was
    if refused:
        warnings.warn(f"{len(refused)} of {len(charts)} charts keep their mesh: "
                      f"{one_line(refused[0])}", ReconstructionWarning, stacklevel=3)
        fresh = [exc is True for exc in fresh]
    retake = [r is True for r in retake]
    atlas.timings_["remesh charts"] = time.perf_counter() - started
    if (any(fresh) or atlas.__dict__.get("_joined_up") != atlas._up_key()
            or not _mesh_stands(atlas)):
        atlas._join(decide=False, fresh=retake)
        moved, nodes = atlas._sdf.n_changed_, atlas._sdf.n_evaluated_
    else:  # every chart's part as it was: the same samples, the same mesh
        atlas.timings_["join"], moved, nodes = 0.0, 0, 0
    atlas.timings_["remesh"] = time.perf_counter() - started
    atlas.remesh_counts_ = {"charts meshed": sum(fresh), "samples moved": moved,
                            "nodes evaluated": nodes,
                            "charts in the worker": in_worker}
    log.info("atlas re-meshed: %d of %d charts meshed, %d of %d join samples changed, %d "
             "nodes evaluated (%.0f ms)", sum(fresh), len(charts), moved,
             len(atlas.samples_), nodes, 1000 * atlas.timings_["remesh"])
    return atlas.mesh_


def _mesh_stands(atlas) -> bool:
    """Whether the atlas's ``mesh_`` is the join of the charts' parts as they are: it is,
    unless the atlas was loaded and has not joined since; then the mesh its join's grid kept
    (the same samples: `join.kept_mesh`) is taken if there is one."""
    if "mesh_" in vars(atlas):
        return True
    grid = atlas.__dict__.get("_sdf")
    mesh = None if grid is None else kept_mesh(grid, trim=atlas.trim, closed=atlas.closed_,
                                               seal=atlas.seal_)
    if mesh is None:
        return False
    atlas.mesh_, atlas.samples_, atlas.normals_ = mesh, grid.samples_, grid.normals_
    atlas.watertight_, atlas.winding_consistent_, atlas.euler_ = topology(mesh.faces)
    atlas._joined_up = atlas._up_key()
    return True


def _worker_for(atlas) -> ChartWorker | None:
    """The `ChartWorker`, taken for this re-mesh, when ``atlas`` may use it (enough charts, a
    process that may start one, ``n_jobs`` not 1) and no other re-mesh has it; else None."""
    if len(atlas.charts_) < MIN_CHARTS or n_chart_workers(atlas.n_jobs) < 1:
        return None
    worker = shared_worker()
    return worker if worker.acquire() else None


def _remesh_here(atlas, indices, parts, params: dict) -> list:
    """`_remesh_chart` of the charts ``indices``, in threads."""
    indices = list(indices)
    with ThreadPoolExecutor(max(1, min(REMESH_THREADS, len(indices)))) as pool:
        return list(pool.map(lambda i: _remesh_chart(
            atlas, i, None if parts is None else parts[i], params), indices))


def _remesh_beside(worker: ChartWorker, atlas, parts, params: dict) -> tuple[list, list, int]:
    """Re-mesh the charts here from the first and in the worker from the last until the two
    meet; a worker that fails leaves its charts to this process. A chart's error that is not
    its boundary's (as `_remesh_chart` would raise) is raised. Returns each chart's result,
    which charts' parts of the join are to be taken again (the others' were) and how many
    charts the worker meshed. (Moving the join's grid to this process's charts while the
    worker meshes its last ones was measured slower, 2026-12-06: the grid's update costs
    about as much for a third of the moved samples as for all of them, its boxes round the
    changes spanning most of the grid; mug 22k, a re-mesh's median 295 -> 353 ms.)"""
    n = len(atlas.charts_)
    asked = worker.submit(atlas, parts, params)
    fresh = {}
    try:
        for i in range(n):
            if asked and not worker.take(i):
                break
            fresh[i] = _remesh_chart(atlas, i, None if parts is None else parts[i], params)
        if parts is not None:  # the join's parts of ours, taken while the worker works
            atlas._chart_parts([fresh.get(i) is True for i in range(n)])
    except BaseException:
        if asked:
            worker.results()  # this re-mesh's answer, read so the next one reads its own
        raise
    results = worker.results() if asked else None
    theirs = [i for i in range(n) if i not in fresh]
    if results is None or set(theirs) - set(results):
        fresh.update(zip(theirs, _remesh_here(atlas, theirs, parts, params), strict=True))
        return [fresh[i] for i in range(n)], [fresh[i] is True and i in theirs
                                              for i in range(n)], 0
    for i in theirs:
        result, said = results[i]
        for message in said:
            warnings.warn(message, ReconstructionWarning, stacklevel=2)
        if isinstance(result, Exception) and not isinstance(result, (FitError,
                                                                     DegenerateCloudError)):
            raise result
        fresh[i] = apply(atlas.charts_[i], params, result)
        if parts is not None and part_given(result) is not None:
            atlas._parts[i] = part_given(result)
    return [fresh[i] for i in range(n)], [False] * n, len(theirs)


def _remesh_chart(atlas, index: int, part: ChartPart | None,
                  params: dict) -> bool | ReconstructionError:
    """Re-mesh chart ``index`` with ``params`` unless its ``part`` of the join cannot change
    (`chart_parts.unchanged`); returns whether it was meshed, or the error of a chart whose
    boundary cannot take them (a small chart's spline that a large λ collapses, too few points
    at a depth: the chart keeps its parameters and mesh)."""
    labels_tree = atlas.__dict__.get("_owners")  # else not joined since loaded or fitted
    return remesh_chart(atlas.charts_[index], index, part if labels_tree else None, params,
                        labels_tree, atlas.reach * atlas.decomposition_.spacing_)
