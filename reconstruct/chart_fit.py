"""Fitting an atlas's charts: one chart with the paper's pipeline (`fit_chart`), many at once
in this process and a pool of worker processes (`chart_workers`, `fit_charts`), and all of a
decomposition's, unfaithful ones split, and then those that leave a shape in their residuals
(`fit_every_chart`, `split_underfit`); charts embedded ahead on idle workers (`ChartsAhead`).

A chart is a `SurfaceReconstructor` fitted without the atlas fallback, then judged faithful or
not (`faithfulness`: unexplained points, fold-over, points in two layers), pinned to its grid
lattice and sampled at every saved boundary depth, so the atlas re-meshes it incrementally and
to any of those depths.
"""

from __future__ import annotations

import logging
import multiprocessing
import threading
import time
import warnings
from collections import deque
from concurrent.futures import FIRST_COMPLETED
from concurrent.futures import wait as wait_for
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from joblib import effective_n_jobs
from joblib.externals.loky import ProcessPoolExecutor

from .chart_logs import chart_steps
from .errors import ReconstructionWarning
from .faithfulness import (
    FOLD_LIMIT,
    LAYERED_KURTOSIS,
    TWO_LAYER_KURTOSIS,
    UNEXPLAINED_LIMIT,
    fold_share,
    residual_kurtosis,
    residual_structure,
)
from .io import one_line
from .meshing import default_spacing
from .threads import single_threaded

if TYPE_CHECKING:
    from .pipeline import Embedded

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
#: A chart fitted with the first chart's searched layers gets at most one network parameter
#: per this many of its points (`sized_layers`): a small chart would fit its noise with the
#: first's. Chair 20k: 51 of its 115 charts have under 300 points, and the first's (10, 9)
#: (159 parameters) left their samples 0.70 mm RMS from the true chair against 0.43 on the
#: large charts (σ 0.86); with the layers narrowed, its denoise ratio 0.514 -> 0.494.
POINTS_PER_PARAMETER = 2
#: A chart whose residuals' variance its points' nearest neighbours share above this part
#: (`faithfulness.residual_structure`: noise shares none) leaves a shape its network could not
#: hold, and is fitted again in two parts, once (`split_underfit`); not a chart whose points lie
#: in two layers about it (residual kurtosis under `LAYERED_KURTOSIS`: a wall thinner than the
#: noise, whose layers share their residuals too and which no split fits: the tray's). Above it
#: at 20k points, σ 0.5 %: the scanned dragon's 58 charts of 123 (scales, claws), the figurine's
#: 23 of 50, the chair's 15 of 115 (sharp edges), the mug's 2 of 41. bench.atlas 20k, seeds
#: 0 / 1 / 2, Chamfer-L1 before / after: dragon 0.344 / 0.328, 0.350 / 0.332, 0.356 / 0.344;
#: figurine 0.163 / 0.153, 0.173 / 0.163, 0.152 / 0.154; relief (σ 1 %) 0.549 / 0.493, 0.548 /
#: 0.453, 0.556 / 0.532; chair 0.296 / 0.299, 0.264 / 0.273, 0.254 / 0.258 (denoise at most
#: 0.469); sheets at seed 1 merged (gap 91 % open), now 100 %; the tray's Euler at seed 2 −4,
#: now 2. Splitting the parts again brought the dragon to 0.323 at seed 0 but merged the sheets;
#: without the layers' exception, the tray's Euler at seed 1 was −4 (2 before).
UNDERFIT_SHARE = 0.5
#: ... and whose points' neighbours along the mesh share it too, this many standard errors
#: above what noise alone gives (`faithfulness.residual_structure`): where the noise nears the
#: spacing, neighbours in space share it (every chart of a smooth torus at σ 1 %: 0.57-0.59,
#: along the mesh z −2.2-1.4), and so do the two layers of a wall thinner than the noise whose
#: kurtosis is over `LAYERED_KURTOSIS` (8 of the tray's 25 charts above half at seed 2: z under
#: 3). Splitting charts that hold their shape cost more than it brought: bench.atlas --noise
#: 0.01, seed 0, Chamfer-L1 before the split / with it / with this: torus 0.186 / 0.224 /
#: 0.186, knot 0.292 / 0.325 / 0.310, figurine 0.317 / 0.344 / 0.326, bunny 0.392 / 0.374 /
#: 0.363; at σ 0.5 % (seeds 0-2) the dragon's, relief's, chair's and sheets' are unchanged.
UNDERFIT_Z = 3.0
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _import_pipeline() -> None:
    from . import pipeline  # noqa: F401
    from .networks import load_torch

    load_torch()


def _chart_params(n_points: int, lam: float, depth: int, random_state,
                  n_neighbors: int | None) -> dict:
    """`SurfaceReconstructor` parameters of a chart of ``n_points``."""
    return dict(lam=lam, depth=depth, random_state=random_state, atlas="never", up=None,
                embedding="landmark" if n_points > LANDMARK_CHARTS else "auto",
                n_neighbors=n_neighbors)


def embed_chart(points, lam: float, depth: int, random_state, n_neighbors: int) -> Embedded:
    """The start of `fit_chart` that needs no layers (`SurfaceReconstructor.embed`): the chart's
    embedding with K ``n_neighbors`` and its boundary samples at every saved depth."""
    from .pipeline import SurfaceReconstructor

    with chart_steps():
        return SurfaceReconstructor(**_chart_params(len(points), lam, depth, random_state,
                                                    n_neighbors)).embed(points, SAVED_DEPTHS)


def fit_chart(points, lam: float, depth: int, random_state, n_neighbors: int | None = None,
              hidden_layers: tuple[int, ...] | None = None,
              embedded: Embedded | None = None, search: dict | None = None,
              sized: bool = False) -> tuple:
    """Fit one chart (m, 3) with the paper's pipeline: a search (``search``: `AdaptiveMLP`'s
    limits, ``max_layers`` and ``max_neurons``), or the given ``hidden_layers`` (``sized``:
    narrowed to the chart's points, `sized_layers`) and K (``embedded``: `embed_chart`'s of
    these points, taken up). Returns (fitted `SurfaceReconstructor` or None, fault or None):
    the fault says why the chart is not faithful (`faithfulness`) or could not be fitted."""
    with chart_steps():
        return _fit_chart(points, lam, depth, random_state, n_neighbors, hidden_layers,
                          embedded, search, sized)


def _fit_chart(points, lam, depth, random_state, n_neighbors, hidden_layers, embedded, search,
               sized) -> tuple:
    from .mlp import AdaptiveMLP
    from .pipeline import SurfaceReconstructor

    params = _chart_params(len(points), lam, depth, random_state, n_neighbors)
    if hidden_layers is not None and sized:
        hidden_layers = sized_layers(hidden_layers, len(points))
    if hidden_layers is not None:
        params.update(mlp=AdaptiveMLP(
            hidden_layers=hidden_layers, final_starts=CHART_FINAL_STARTS,
            random_state=random_state))
    else:  # the first chart's search, as a one-chart fit's but without its weight decay
        params.update(mlp=AdaptiveMLP(random_state=random_state, **(search or {})))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ReconstructionWarning)
            reconstructor = SurfaceReconstructor(**params)
            reconstructor._atlas_chart = True
            reconstructor.fit(points, embedded=embedded)
    except Exception as exc:  # a chart the method cannot fit is split, never hidden
        log.info("a chart of %d points failed to fit: %s", len(points), exc)
        return None, f"fit failed ({one_line(exc)})"
    faults = []
    if reconstructor.unexplained_ > UNEXPLAINED_LIMIT:
        faults.append(f"{100 * reconstructor.unexplained_:.0f} % of its points unexplained")
    folds = fold_share(reconstructor.mesh_)
    if folds > FOLD_LIMIT:
        faults.append(f"mesh folds over ({100 * folds:.1f} % of its edges)")
    kurtosis = residual_kurtosis(reconstructor.mesh_, points)
    if kurtosis < TWO_LAYER_KURTOSIS:
        faults.append(f"its points lie in two layers, one each side of its mesh (residual "
                      f"kurtosis {kurtosis:.2f}): two sheets meshed as one")
    reconstructor.fold_share_ = folds
    ready_to_remesh(reconstructor)
    return reconstructor, ("; ".join(faults) or None)


def network_parameters(layers: tuple[int, ...]) -> int:
    """Weights and biases of a chart's network, 2 inputs → ``layers`` → 3 outputs."""
    widths = (2, *layers, 3)
    return sum((a + 1) * b for a, b in zip(widths[:-1], widths[1:], strict=True))


def sized_layers(layers: tuple[int, ...], n_points: int) -> tuple[int, ...]:
    """``layers`` narrowed in proportion (each at least 2 wide) until the network has at most
    ``n_points`` / `POINTS_PER_PARAMETER` parameters, or as narrow as that goes."""
    layers = tuple(int(w) for w in layers)
    limit = n_points / POINTS_PER_PARAMETER
    for scale in np.linspace(1.0, 0.0, 41):
        narrowed = tuple(max(2, round(w * scale)) for w in layers)
        if network_parameters(narrowed) <= limit:
            return narrowed
    return narrowed


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
    chart.sample_boundaries(SAVED_DEPTHS)


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


def fit_charts(clouds: list[np.ndarray], workers=None, embedded=None, **params) -> list[tuple]:
    """`fit_chart` of each of ``clouds`` (each (m_i, 3)) with ``params`` (``embedded``: None, or
    for each cloud its `embed_chart` or None); returns its results in order. With ``workers``
    (`chart_workers`), they take the largest charts first and this process the smallest, until
    the two meet."""
    embedded = embedded or [None] * len(clouds)
    if workers is None or len(clouds) == 1:
        return [fit_chart(cloud, embedded=ahead, **params)
                for cloud, ahead in zip(clouds, embedded, strict=True)]
    largest_first = np.argsort([-len(cloud) for cloud in clouds], kind="stable")
    try:
        futures = {i: workers.submit(fit_chart, clouds[i], embedded=embedded[i], **params)
                   for i in largest_first}
    except RuntimeError as exc:  # the pool broke while idle (a worker killed)
        log.warning("chart workers unavailable (%s); fitting the charts here", one_line(exc))
        return fit_charts(clouds, None, embedded, **params)
    results, said = {}, False
    with single_threaded():  # one core here, the others the workers'
        for i in largest_first[::-1]:
            if not futures[i].cancel():  # a worker has it, and every larger one
                break
            results[i] = fit_chart(clouds[i], embedded=embedded[i], **params)
        for i, future in futures.items():
            if i not in results:
                try:
                    results[i] = future.result()
                except Exception as exc:  # noqa: BLE001 - the worker died: `fit_chart` itself
                    # returns a chart's own failure
                    if not said:  # once: a dead worker breaks the pool, and every chart left
                        log.warning("a chart worker failed (%s); fitting its charts here",
                                    one_line(exc))
                        said = True
                    results[i] = fit_chart(clouds[i], embedded=embedded[i], **params)
    return [results[i] for i in range(len(clouds))]


def fit_every_chart(decomposition, points, workers, params: dict, hidden_layers,
                    reuse_layers: bool, max_splits: int, ahead: dict,
                    started: float, search: dict | None = None) -> tuple[dict, list[str]]:
    """Fit every chart of ``decomposition`` (a fitted `ChartDecomposition` of ``points``
    (m, 3)) by `fit_charts` with ``params`` (`embed_chart`'s) and ``hidden_layers`` (None: the
    first chart searches them, and with ``reuse_layers`` its layers and K serve the others),
    splitting an unfaithful chart up to ``max_splits`` times along one line of descent.
    ``ahead``: {chart index: `Embedded`} of charts embedded ahead with ``params`` (taken up,
    and emptied); ``started``: the fit's start (`time.perf_counter`), for the log; ``search``:
    the limits of the first chart's search (`fit_chart`). Returns
    ({chart index: (fitted `SurfaceReconstructor` or None, its point indices)}, the faults
    left)."""
    fitted: dict[int, tuple] = {}
    faults = []
    queue = [(index, 0) for index in range(decomposition.n_charts_)]
    first = None  # the first fitted chart: its searched layers and K are the others'
    unfaithful = set()  # charts kept with a fault (split max_splits times): said, not split

    def fit(clouds, embedded=None):
        """`fit_charts` of ``clouds`` as the charts are fitted now: with the first chart's
        searched layers and K once there is one (``reuse_layers``), else searching."""
        chart_params, layers = dict(params), hidden_layers
        taken = first is not None and reuse_layers
        if taken:
            chart_params["n_neighbors"], layers = first.n_neighbors_, first.hidden_layers_
        if chart_params["n_neighbors"] != params["n_neighbors"]:  # embedded with another K
            embedded = None
        return fit_charts(clouds, workers, embedded, hidden_layers=layers, search=search,
                          sized=taken, **chart_params)

    while queue:
        # until one chart has searched the layers, one at a time; then all waiting at once
        alone = first is None and hidden_layers is None
        batch, queue = (queue[:1], queue[1:]) if alone else (queue, [])
        members = [decomposition.chart(index) for index, _ in batch]
        embedded = [ahead.pop(index, None) if not splits else None for index, splits in batch]
        results = fit([points[m] for m in members], embedded)
        for (index, splits), chart, (reconstructor, fault) in zip(
                batch, members, results, strict=True):
            if fault is not None and splits < max_splits and len(
                    decomposition.cores_[index]) >= 2 * decomposition.min_points:
                new = decomposition.split(index)
                log.info("chart %d: %s; split in %d", index, fault, len(new))
                queue += [(i, splits + 1) for i in new]
                fitted.pop(index, None)
                continue
            if fault is not None:
                faults.append(f"chart {index} ({len(chart)} points): {fault}")
                unfaithful.add(index)
            if first is None and reconstructor is not None:
                first = reconstructor
            fitted[index] = (reconstructor, chart)
        log.info("%d of %d charts fitted (%.0f s so far)", len(fitted),
                 decomposition.n_charts_, time.perf_counter() - started)
    if first is not None:
        split = split_underfit(decomposition, points, fitted, fit, skip=unfaithful)
        if split:
            log.info("%d charts left a shape in their residuals: split (%d charts, %.0f s so "
                     "far)", split, decomposition.n_charts_, time.perf_counter() - started)
    return fitted, faults


def split_underfit(decomposition, points, fitted: dict, fit, skip=()) -> int:
    """Split each of the ``fitted`` charts ({index: (reconstructor or None, point
    indices)} of ``decomposition`` of ``points`` (m, 3)) whose residuals keep a shape and are
    not in two layers (`UNDERFIT_SHARE`) in the parts `split_cells` proposes, fitted by ``fit``
    (a list of clouds → `fit_charts`' results), when every part is faithful; not the charts
    ``skip`` (indices: those kept with a fault, which a warning names). Updates ``fitted`` and
    the decomposition; returns how many charts were split."""
    proposals = []
    for index, (reconstructor, members) in fitted.items():
        if (reconstructor is None or index in skip
                or len(decomposition.cores_[index]) < 2 * decomposition.min_points):
            continue
        variance, shared, z_along = residual_structure(reconstructor.mesh_, points[members])
        if (shared > UNDERFIT_SHARE * variance > 0 and z_along >= UNDERFIT_Z
                and residual_kurtosis(reconstructor.mesh_, points[members]) >= LAYERED_KURTOSIS):
            cells = decomposition.split_cells(index)
            if len(cells) > 1:
                proposals.append((index, cells))
    if not proposals:
        return 0
    clouds = [decomposition.members(cell) for _, cells in proposals for cell in cells]
    results = iter(zip(fit([points[m] for m in clouds]), clouds, strict=True))
    n_split = 0
    for index, cells in proposals:
        parts = [next(results) for _ in cells]
        if any(reconstructor is None or fault is not None
               for (reconstructor, fault), _ in parts):
            continue  # the chart is faithful; its parts would not all be
        for new, ((reconstructor, _), members) in zip(
                decomposition.split(index, cells=cells), parts, strict=True):
            fitted[new] = (reconstructor, members)
        n_split += 1
    return n_split


class ChartsAhead:
    """Charts embedded ahead (`embed_chart`) by idle workers: once the decomposition's future
    is back, each of its charts in turn, one a worker at a time, until `stop`. A one-chart fit
    searching its net leaves the workers idle for seconds (rough 20k: 4 s after the
    decomposition); an atlas's chart embedded ahead starts at training its network (the
    embedding and boundary sampling it skips are a third of a chart's fit)."""

    def __init__(self, workers, n_workers: int, decomposition, points, **params):
        self.params = params  # `embed_chart`'s: a fit with others cannot take them up
        self._embedded: dict[int, Embedded] = {}
        self._stopping = threading.Event()
        self._collect = False
        self._thread = threading.Thread(
            target=self._run, args=(workers, max(n_workers, 1), decomposition, points),
            name="charts ahead", daemon=True)
        self._thread.start()

    def _run(self, workers, n_workers, decomposition, points) -> None:
        try:
            decomposition = decomposition.result()
        except BaseException:  # noqa: BLE001 - the fit that takes the decomposition up says why
            return
        waiting, running = deque(range(decomposition.n_charts_)), {}
        while (waiting or running) and not self._stopping.is_set():
            while waiting and len(running) < n_workers:
                index = waiting.popleft()
                try:
                    future = workers.submit(embed_chart, points[decomposition.chart(index)],
                                            **self.params)
                except RuntimeError:  # the pool shut down: nothing more to do ahead
                    return
                running[future] = index
            done, _ = wait_for(running, timeout=0.05, return_when=FIRST_COMPLETED)
            self._take(done, running)
        if self._collect:  # a worker has them: their results are a moment away
            self._take(wait_for(running).done, running)

    def _take(self, done, running: dict) -> None:
        for future in done:
            index = running.pop(future)
            if not future.cancelled() and future.exception() is None:
                self._embedded[index] = future.result()

    def stop(self, collect: bool = False) -> dict:
        """Embed no further chart; returns {chart index: `Embedded`} of the charts embedded
        (``collect``: with those being embedded now, waited for)."""
        self._collect = collect
        self._stopping.set()
        self._thread.join()
        return self._embedded


class BegunFit(NamedTuple):
    """What `AtlasReconstructor.warm` / `start` began: the points and their charted subset
    (None when only warmed), the worker pool, the decomposition's future (None when only
    warmed), the workers' torch imports (one future each) and the charts they embed ahead
    (`ChartsAhead`, or None)."""

    points: object
    charted: object
    workers: object
    decomposition: object
    warming: list
    ahead: ChartsAhead | None = None

    def idle(self) -> tuple:
        """(the pool, its number of workers) once they have imported torch and decomposed
        the cloud if asked, or (None, 0); charts are no longer embedded ahead."""
        if not all(  # done, and well: a failed import says the pool is not
                f.done() and not f.cancelled() and f.exception() is None
                for f in (self.decomposition, *self.warming) if f is not None):
            return None, 0
        if self.ahead is not None:
            self.ahead.stop()
        return self.workers, len(self.warming)  # one import per worker

    def stop(self) -> None:
        """Wait for a decomposition, then stop the workers in their torch import (waiting for
        it cost a 20k sphere cap's one-chart fit 2.2 s). Loky's `kill_workers` earlier than
        that left a worker blocked sending its result, or its manager thread raised on an item
        not yet dispatched."""
        if self.ahead is not None:
            self.ahead.stop(collect=True)  # none being sent when the workers are stopped
        if self.decomposition is not None:
            wait_for([self.decomposition])
        deadline = time.monotonic() + 10.0
        while not all(f.running() or f.done() for f in self.warming):  # dispatched, in a moment
            if time.monotonic() > deadline:
                self.workers.shutdown(wait=True)
                return
            time.sleep(0.005)
        self.workers.shutdown(wait=True, kill_workers=True)
