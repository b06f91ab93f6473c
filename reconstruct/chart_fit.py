"""Fitting an atlas's charts: one chart with the paper's pipeline (`fit_chart`), and many at
once in this process and a pool of worker processes (`chart_workers`, `fit_charts`).

A chart is a `SurfaceReconstructor` fitted without the atlas fallback, then judged faithful or
not (`faithfulness`: unexplained points, fold-over), pinned to its grid lattice and sampled at
every saved boundary depth, so the atlas re-meshes it incrementally and to any of those depths.
"""

from __future__ import annotations

import logging
import multiprocessing
import time
import warnings
from concurrent.futures import wait as wait_for
from typing import NamedTuple

import numpy as np
from joblib import effective_n_jobs
from joblib.externals.loky import ProcessPoolExecutor

from .errors import ReconstructionWarning
from .faithfulness import FOLD_LIMIT, UNEXPLAINED_LIMIT, fold_share
from .io import one_line
from .meshing import default_spacing
from .threads import single_threaded

log = logging.getLogger(__name__)

#: Boundary depths whose samples `fit` computes (and `state` saves) for every chart, so a
#: fitted or loaded atlas re-meshes to another of them without sampling its boundaries first.
SAVED_DEPTHS = (1, 2, 3)
#: Charts of more points than this are embedded by landmark Isomap: full Isomap's all-pairs
#: geodesics took a third of an atlas's fit (rough 20k, 47 charts: 9.5 of 27 s). On 500-3,000
#: point terrains landmark Isomap ran 4-28x faster with the same residual variance (to 1e-4).
LANDMARK_CHARTS = 400
#: Fresh starts of a chart's final fits beside its first (`AdaptiveMLP.final_starts`): the
#: join averages overlapping charts anyway. Rough 20k (layers (15, 15), 47 charts): Chamfer
#: 0.00653 with one, 0.00652 with two; relief 20k 0.5357 against 0.5372; fits 8.3 s against 10.6.
CHART_FINAL_STARTS = 1
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _import_pipeline() -> None:
    from . import pipeline  # noqa: F401
    from .networks import load_torch

    load_torch()


def fit_chart(points, lam: float, depth: int, random_state, n_neighbors: int | None = None,
              hidden_layers: tuple[int, ...] | None = None) -> tuple:
    """Fit one chart (m, 3) with the paper's pipeline: a search, or the given ``hidden_layers``
    and K. Returns (fitted `SurfaceReconstructor` or None, fault or None): the fault says why
    the chart is not faithful (`faithfulness`) or could not be fitted."""
    from .mlp import AdaptiveMLP
    from .pipeline import SurfaceReconstructor

    params = dict(lam=lam, depth=depth, random_state=random_state, atlas="never", up=None,
                  embedding="landmark" if len(points) > LANDMARK_CHARTS else "auto",
                  n_neighbors=n_neighbors)
    if hidden_layers is not None:
        params.update(mlp=AdaptiveMLP(
            hidden_layers=hidden_layers, final_starts=CHART_FINAL_STARTS,
            random_state=random_state))
    else:  # the first chart's search, as a one-chart fit's but without its weight decay
        params.update(mlp=AdaptiveMLP(random_state=random_state))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ReconstructionWarning)
            reconstructor = SurfaceReconstructor(**params).fit(points)
    except Exception as exc:  # a chart the method cannot fit is split, never hidden
        log.info("a chart of %d points failed to fit: %s", len(points), exc)
        return None, f"fit failed ({one_line(exc)})"
    faults = []
    if reconstructor.unexplained_ > UNEXPLAINED_LIMIT:
        faults.append(f"{100 * reconstructor.unexplained_:.0f} % of its points unexplained")
    folds = fold_share(reconstructor.mesh_)
    if folds > FOLD_LIMIT:
        faults.append(f"mesh folds over ({100 * folds:.1f} % of its edges)")
    reconstructor.fold_share_ = folds
    ready_to_remesh(reconstructor)
    return reconstructor, ("; ".join(faults) or None)


def ready_to_remesh(chart) -> None:
    """Pin a fitted chart's grid spacing (its ``grid_spacing``) and mesh it again on the lattice
    of that spacing, where a new outline leaves the interior be (the join's samples stay put);
    and sample its boundary at each of `SAVED_DEPTHS` (cached, saved with its state), so a
    re-mesh to one of those depths need not sample first (a first depth change took 793 ms
    against 277 for a new λ, torus 22k, 35 charts)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReconstructionWarning)  # said by the fit already
        if chart.grid_spacing is None:
            chart.remesh(grid_spacing=default_spacing(chart.outline_, len(chart.embedding_)))
    depth = chart.depth
    try:
        for saved_depth in SAVED_DEPTHS:
            chart.depth = saved_depth
            chart._boundary_points()
    finally:
        chart.depth = depth


def chart_workers(n_jobs: int | None, warm: bool = True):
    """A pool of ``n_jobs`` − 1 worker processes of its own (joblib's convention: -1 every
    core; the calling process fits charts too), or None for one. Not loky's shared reusable
    pool: shutting that down stopped joblib's, or a second atlas's fitted in another thread.
    Started at once, importing torch and the pipeline (~2 s of a core each), so they are ready
    when the cloud is decomposed (``warm=False``: not yet, `warm_up`); the caller shuts them
    down when done (a process exiting joins its children first). A daemonic process (a Dask
    worker) cannot start any."""
    n_workers = n_chart_workers(n_jobs)
    if n_workers < 1:
        return None
    executor = ProcessPoolExecutor(max_workers=n_workers,
                                   env={name: "1" for name in _THREAD_VARIABLES})
    if warm:
        warm_up(executor, n_workers)
    return executor


def n_chart_workers(n_jobs: int | None) -> int:
    """Worker processes `chart_workers` starts for ``n_jobs``: none in a daemonic process."""
    return 0 if multiprocessing.current_process().daemon else effective_n_jobs(n_jobs) - 1


def warm_up(workers, n_workers: int) -> list:
    """Have each of the ``n_workers`` ``workers`` import torch and the pipeline; returns the
    futures."""
    return [workers.submit(_import_pipeline) for _ in range(n_workers)]


def fit_charts(clouds: list[np.ndarray], workers=None, **params) -> list[tuple]:
    """`fit_chart` of each of ``clouds`` (each (m_i, 3)) with ``params``; returns its results in
    order. With ``workers`` (`chart_workers`), they take the largest charts first and this
    process the smallest, until the two meet."""
    if workers is None or len(clouds) == 1:
        return [fit_chart(cloud, **params) for cloud in clouds]
    largest_first = np.argsort([-len(cloud) for cloud in clouds], kind="stable")
    futures = {i: workers.submit(fit_chart, clouds[i], **params) for i in largest_first}
    results = {}
    with single_threaded():  # one core here, the others the workers'
        for i in largest_first[::-1]:
            if not futures[i].cancel():  # a worker has it, and every larger one
                break
            results[i] = fit_chart(clouds[i], **params)
    for i, future in futures.items():
        if i not in results:
            results[i] = future.result()
    return [results[i] for i in range(len(clouds))]


class BegunFit(NamedTuple):
    """What `AtlasReconstructor.warm` / `start` began: the points and their charted subset
    (None when only warmed), the worker pool, the decomposition's future (None when only
    warmed) and the workers' torch imports (one future each)."""

    points: object
    charted: object
    workers: object
    decomposition: object
    warming: list

    def idle(self) -> tuple:
        """(the pool, its number of workers) once they have imported torch and decomposed
        the cloud if asked, or (None, 0)."""
        if not all(  # done, and well: a failed import says the pool is not
                f.done() and not f.cancelled() and f.exception() is None
                for f in (self.decomposition, *self.warming) if f is not None):
            return None, 0
        return self.workers, len(self.warming)  # one import per worker

    def stop(self) -> None:
        """Wait for a decomposition, then stop the workers in their torch import (waiting for
        it cost a 20k sphere cap's one-chart fit 2.2 s). Loky's `kill_workers` earlier than
        that left a worker blocked sending its result, or its manager thread raised on an item
        not yet dispatched."""
        if self.decomposition is not None:
            wait_for([self.decomposition])
        deadline = time.monotonic() + 10.0
        while not all(f.running() or f.done() for f in self.warming):  # dispatched, in a moment
            if time.monotonic() > deadline:
                self.workers.shutdown(wait=True)
                return
            time.sleep(0.005)
        self.workers.shutdown(wait=True, kill_workers=True)
