"""Any surface with the paper's method: an atlas of charts, each fitted by `SurfaceReconstructor`,
joined into one mesh.

`AtlasReconstructor.fit` splits the cloud into overlapping disc-like charts
(`reconstruct.charts` on the sheet-respecting graph of `reconstruct.sheet_graph`), fits each
with the paper's pipeline (embedding → adaptive MLP → multi-depth boundary → spline → mesh →
ONNX map; the first chart's searched layer widths and K, or those of a one-chart fit of the
same cloud, are reused by the others, which then train without a search, in ``n_jobs``
processes: `reconstruct.chart_fit`), and accepts a chart only when it is faithful: its mesh
leaves at most `UNEXPLAINED_LIMIT` of its points unexplained, does not fold over
(`fold_share`) and does not run between two layers of its points (`residual_kurtosis`);
otherwise the chart is split and fitted again (at most ``max_splits`` times
along one line of descent). A faithful chart whose residuals keep a shape its network could not
hold (neighbouring points' residuals alike: `chart_fit.split_underfit`) is fitted again in two
parts, kept when both are faithful.
The accepted charts' meshes, trimmed to a partition of the cloud, oriented alike (along their
overlaps, and by which side of each is outside: `reconstruct.chart_sides`) and joined by
`reconstruct.join.implicit_mesh`, give ``mesh_``: when the charts enclose a volume, its
boundary (watertight; a part thinner than the noise, charted as one sheet, as a thin shell, and
so a thin part charted on one face with the data of its far face left out of the charts just
behind it, whose shell keeps the gap that data faces open: two plates a few noise widths
apart; a warning if it still is not watertight); otherwise open where the data has a border
or a hole wider than a few spacings.

`remesh(lam=..., depth=...)` re-meshes every chart through its stored ONNX map (no retraining)
and joins them again, re-evaluating the join's grid only round the samples that moved
(`reconstruct.atlas_remesh`, `reconstruct.sdf_grid`, `reconstruct.closed_grid`). `save` /
`load` (and `SurfaceReconstructor.save` / `load` of an atlas) carry the charts' maps, the
partition, the signs and the join's last samples and mesh to another process, where `remesh`
runs without torch.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import trimesh
from sklearn.base import BaseEstimator

from .atlas_remesh import remesh_atlas
from .atlas_state import ATLAS_FORMAT, atlas_from_state, atlas_state
from .chart_fit import (
    BegunFit,
    ChartsAhead,
    chart_workers,
    fit_every_chart,
    n_chart_workers,
    warm_up,
)
from .chart_logs import chart_steps
from .chart_parts import ChartPart, parts_of
from .chart_sides import (
    ChartSides,
    UnchartedTracker,
    chart_noise,
    two_layer_charts,
    uncharted_points,
    uncharted_reach,
)
from .charts import ChartDecomposition
from .closed_grid import ClosedSDF
from .errors import (
    FitError,
    InvalidInputError,
    NotFittedError,
    ReconstructionWarning,
)
from .faithfulness import (
    LAYERED_KURTOSIS,
    residual_kurtosis,
    sampled_kurtosis,
    volume_warning,
)
from .io import one_line, read_state, write_state
from .join import (
    ExteriorProbe,
    border_vertices,
    check_up,
    faces_seen_side,
    implicit_mesh,
    kept_topology,
    orient_charts,
    owned,
    stretched_samples,
    thin_shell,
)
from .join_alignment import steady_join
from .kdtree import PointTree
from .mesh_edges import topology, turn_faces
from .residual_detail import DETAIL_WIDTH, ResidualDetail
from .sdf_grid import SparseSDF
from .sheet_graph import SheetGraph
from .validation import ATLAS_POINTS, check_points, check_voxel, random_subset

log = logging.getLogger(__name__)

#: In an open join, a chart's faces with an edge this many times longer than its median edge
#: are filled with samples (`join.stretched_samples`; its grid's diagonals are 1.4 times its
#: sides). A closed join closes such gaps itself, and the samples only add noise there
#: (figurine 20k seed 0: Chamfer 0.159 → 0.168).
STRETCHED = 2.0
#: A closed join whose topology depends on where its grid falls advises a voxel this many times
#: larger (`reconstruct.join_alignment`: 0.5 -> 0.7 median spacings steadied uneven samples).
LARGER_VOXEL = 1.4


class AtlasReconstructor(BaseEstimator):
    """Reconstruct one mesh from any surface cloud (n, 3) with an atlas of fitted charts.

    Parameters
    ----------
    chart_size : points in a chart's core (`ChartDecomposition`).
    overlap : ring around each core, in median spacings.
    lam, depth : the charts' spline smoothing and boundary depth (`SurfaceReconstructor`).
    reuse_layers : later charts train the first chart's searched layer widths (no search).
    max_splits : how often an unfaithful chart may be split again.
    voxel : grid spacing of the join, in median point spacings (mean distance to 12 nearest).
    band, trim : `implicit_mesh` band and trim (from the chart samples), in voxels. Trimming
        from the input points instead closed no more holes on the 5k hook and lost accuracy
        (denoise 0.96 against 0.70).
    reach : chart samples farther than this from every point (in median spacings) are dropped,
        so a hole inside a chart's outline stays a hole. Relief 20k σ 1 % (holes 84 and 101 mm
        round): reach 2, trim 1.5 closed both holes; reach 1, trim 1 keeps them (63 and 99 mm
        borders) and measured better (F 0.984 against 0.973, denoise 0.43 against 0.52).
    shell : in a closed cloud, a chart seen from outside on both sides (a part thinner than the
        noise, such as a curled ear, fitted as one sheet) is joined as a closed shell this many
        voxels thick on either side (`join.thin_shell`).
    closed : None: join the charts as the boundary of a volume when their exterior votes say
        the cloud is closed, else as an open surface; False: always open (a scan with unseen
        parts, where a closed join caps guesses: `capture.live.atlas_fit`); True: always closed.
    up : (3,) the direction an open surface is seen from above: its mesh is turned to face
        from above and around, as a station or a scanner over a table sees it
        (`join.faces_seen_side`; None: as its charts' normals give it); a closed one faces out of
        its volume.
    hidden_layers, n_neighbors : the charts' layer widths and K, e.g. of a one-chart fit of the
        same cloud (`SurfaceReconstructor`); None: the first chart's search and choice.
    max_layers, max_neurons : the limits of that search (`AdaptiveMLP`).
    graph : an unfitted `SheetGraph` (its parameters); None: the defaults.
    max_points : a denser cloud is charted, fitted and joined on this many of its points (drawn
        at random; each chart's net trains on at most 6,000 points anyway). At σ 1 % more
        points add noise rather than detail, and the neighbourhoods of the sheet graph and of
        the faithfulness checks shrink below the noise: rough surface 30,000 points, 60 graph
        pieces, Chamfer 0.0070 against 0.0064 at 20,000; at 100,000, 1,275 pieces, 386 charts,
        most split again for 5-12 % unexplained points (over 8 min, 4 GB). 100,000 charted on
        20,000: see bench.speed.
    n_jobs : processes fitting the charts after the first (joblib: -1 every core, 1 none).
        Rough surface 20k, 47 charts, 2 cores: fits 17.0 s in one process, 9.4 s in two
        (12.3 with the workers started cold, 10.6 started while the cloud is decomposed).
    random_state : seed (same seed, same mesh, whatever ``n_jobs``).

    Fitted attributes: ``charts_`` list of fitted `SurfaceReconstructor`, ``chart_points_`` list
    of (m_i,) indices of the points each was fitted to, ``decomposition_``
    (`ChartDecomposition`), ``signs_`` (c,) ±1 orientation of each chart, ``mesh_``
    (trimesh.Trimesh), ``faults_`` one line per chart kept though unfaithful,
    ``watertight_``, ``euler_``, ``winding_consistent_``, ``timings_`` seconds per stage,
    ``votes_`` (c,) each chart's exterior vote (with a band of ``seal_`` voxels), ``shells_``
    (c,) charts joined as thin shells, ``thin_`` (c,) those of them charted on one face of a thin
    part (`reconstruct.chart_sides`), ``noise_`` the charts' median residual RMS (data the charts
    left out lies beyond twice it and a spacing: `chart_sides.uncharted_reach`), ``details_``
    (c,) each chart's `residual_detail.ResidualDetail`, which puts the shape its network left in
    its points' residuals back into its part of the join's samples, ``closed_``
    whether the cloud was joined as the boundary of a volume (then a mesh that is not
    watertight is warned about); after a `remesh`, ``remesh_counts_``: charts meshed, join
    samples moved, grid nodes evaluated, charts re-meshed in the worker process
    (`reconstruct.remesh_worker`; none in a process with ``n_jobs=1``).
    """

    def __init__(self, chart_size: int = 2500, overlap: float = 4.0, lam: float = 1.0,
                 depth: int = 2, reuse_layers: bool = True, max_splits: int = 2,
                 voxel: float = 0.5, band: float = 3.0, trim: float = 1.0, reach: float = 1.0,
                 shell: float = 1.0, closed: bool | None = None,
                 hidden_layers: tuple[int, ...] | None = None, n_neighbors: int | None = None,
                 max_layers: int = 2, max_neurons: int = 20,
                 graph: SheetGraph | None = None, max_points: int | None = ATLAS_POINTS,
                 n_jobs: int | None = -1,
                 up: tuple[float, float, float] | None = (0.0, 0.0, 1.0),
                 random_state: int | None = 0):
        self.chart_size = chart_size
        self.overlap = overlap
        self.lam = lam
        self.depth = depth
        self.reuse_layers = reuse_layers
        self.max_splits = max_splits
        self.voxel = voxel
        self.band = band
        self.trim = trim
        self.reach = reach
        self.shell = shell
        self.closed = closed
        self.up = up
        self.hidden_layers = hidden_layers
        self.max_layers = max_layers
        self.max_neurons = max_neurons
        self.n_neighbors = n_neighbors
        self.graph = graph
        self.max_points = max_points
        self.n_jobs = n_jobs
        self.random_state = random_state

    def warm(self) -> AtlasReconstructor:
        """Start the chart workers importing torch and the pipeline before the cloud to chart
        is known (`start` then gives them the decomposition): `SurfaceReconstructor` warms
        them while it embeds a large cloud, so they are ready for the atlas or for its final
        fits (`idle_workers`). Without workers (``n_jobs=1``, a daemonic process) nothing
        starts."""
        self.cancel()
        workers = chart_workers(self.n_jobs, warm=False)
        if workers is not None:
            self._started = BegunFit(None, None, workers, None,
                                     warm_up(workers, n_chart_workers(self.n_jobs)))
        return self

    def start(self, points) -> AtlasReconstructor:
        """Begin a `fit` of ``points`` (n, 3) in the background, while the caller does other
        work: the chart workers start (or those of `warm` serve), one of them decomposes the
        cloud, and they import torch; with ``n_neighbors`` given, they then embed the charts
        ahead (`chart_fit.ChartsAhead`) until the fit or `idle_workers`. A later
        ``fit(points)`` of the same array takes them up (of the parameters, only
        ``hidden_layers`` and ``n_neighbors`` may change in between: charts embedded with
        another K are embedded again); `cancel` drops them. Without workers (``n_jobs=1``, a
        daemonic process) nothing starts. Until then the estimator holds a process pool: it
        cannot be pickled or copied. Rough 20k: the decomposition (2.1 s) and most charts'
        embeddings run while `SurfaceReconstructor` searches one chart's net, which decides
        whether the atlas is needed."""
        charted = self._charted(check_points(points))
        started = self.__dict__.get("_started")
        if started is not None and started.points is None:  # warmed: not begun on a cloud
            workers, warming = started.workers, started.warming
        else:
            self.cancel()
            workers, warming = chart_workers(self.n_jobs, warm=False), None
        if workers is None:
            return self
        decomposition = workers.submit(self._decomposition().fit, charted)
        if warming is None:  # after the decomposition, which needs no torch
            warming = warm_up(workers, n_chart_workers(self.n_jobs))
        ahead = None if self.n_neighbors is None else ChartsAhead(
            workers, n_chart_workers(self.n_jobs), decomposition, charted,
            **self._embed_params())
        self._started = BegunFit(points, charted, workers, decomposition, warming, ahead)
        return self

    def idle_workers(self) -> tuple:
        """(executor, number of workers) of the pool `warm` or `start` began once it has
        imported torch and decomposed the cloud if asked, or (None, 0): idle, it may serve
        other fitting until `fit` or `cancel`."""
        started = self.__dict__.get("_started")
        return (None, 0) if started is None else started.idle()

    def cancel(self) -> None:
        """Drop what `warm` or `start` began (`chart_fit.BegunFit.stop`)."""
        started = self.__dict__.pop("_started", None)
        if started is not None:
            started.stop()

    def fit(self, points, y=None) -> AtlasReconstructor:
        """points : (n, 3) float. Returns self with ``mesh_`` set."""
        started_with, charted, workers, decomposition, _, ahead = self.__dict__.pop(
            "_started", (None,) * 6)
        if started_with is not points:  # begun for other points: only its workers serve
            decomposition = None
        started = time.perf_counter()
        self.timings_ = {}
        stopping = None
        try:
            try:
                points = check_points(points)
                check_voxel(self.voxel)
                if self.up is not None:
                    check_up(self.up)
                volume = volume_warning(points)
                if volume:
                    warnings.warn(volume, ReconstructionWarning, stacklevel=2)
                if workers is None:
                    workers = chart_workers(self.n_jobs)
                points, fitted = self._fit_all(points, workers, started,
                                               None if decomposition is None
                                               else (charted, decomposition, ahead))
            finally:  # the workers stop on their core while this one joins the charts (rough
                # 20k: 0.55 s of stopping hidden)
                if workers is not None:
                    stopping = threading.Thread(target=workers.shutdown, name="chart workers")
                    stopping.start()
            self._assemble(points, fitted, started)
        finally:  # no worker outlives the fit: a process exiting joins its children first
            if stopping is not None:
                stopping.join()
        return self

    def _assemble(self, points, fitted: dict, started: float) -> None:
        """Take the fitted charts (`_fit_all`'s), orient and join them."""
        order = sorted(i for i in fitted if fitted[i][0] is not None)
        if not order:
            raise FitError(f"no chart of the atlas could be fitted: {self.faults_[0]}")
        self.charts_ = [fitted[i][0] for i in order]
        self.chart_points_ = [fitted[i][1] for i in order]
        self._chart_ids = order
        for name in ("_owners", "_parts", "_sdf", "_detail_kept"):  # a fit's join starts afresh
            self.__dict__.pop(name, None)
        self.timings_["fits"] = time.perf_counter() - started - self.timings_["charts"]
        self.signs_ = orient_charts([c.mesh_ for c in self.charts_], self.chart_points_, points)
        width = DETAIL_WIDTH * self.decomposition_.spacing_
        self.details_ = [ResidualDetail(width).fit(c.mesh_, points[np.asarray(members)])
                         for c, members in zip(self.charts_, self.chart_points_, strict=True)]
        self.noise_ = chart_noise([d.residuals_ for d in self.details_])
        self._join()
        self.timings_["total"] = time.perf_counter() - started
        log.info("atlas: %d charts, %d faces, watertight %s, Euler %d (%.1f s)",
                 len(self.charts_), len(self.mesh_.faces), self.watertight_, self.euler_,
                 self.timings_["total"])

    def _charted(self, points: np.ndarray) -> np.ndarray:
        """The points (m, 3) the atlas charts: all, or a random ``max_points`` of a denser
        cloud (denser adds noise, not detail)."""
        charted = random_subset(points, self.max_points, self.random_state)
        if len(charted) < len(points):
            log.info("atlas of %d of the %d points (max_points; more keep finer detail, in "
                     "more time: --atlas-points N, with --max-points N or all)", len(charted),
                     len(points))
        return charted

    def _decomposition(self) -> ChartDecomposition:
        """An unfitted `ChartDecomposition` with this atlas's parameters."""
        return ChartDecomposition(chart_size=self.chart_size, overlap=self.overlap,
                                  graph=self.graph, random_state=self.random_state)

    def _fit_all(self, points, workers, started, begun=None) -> tuple[np.ndarray, dict]:
        """Decompose ``points`` (a subset of them beyond ``max_points``), or take up what
        `start` began (``begun``: the points it charted, its decomposition's future and the
        charts it embeds ahead or None), and fit every chart, splitting unfaithful ones.
        Returns (the points charted, {chart: (reconstructor or None, its point indices)})."""
        ahead = {}  # chart index: its `Embedded`, when embedded ahead with this fit's K
        if begun is None:
            points = self._charted(points)
            decomposition = self._decomposition().fit(points)
        else:
            points = begun[0]
            try:
                decomposition = begun[1].result()
            except Exception as exc:  # noqa: BLE001 - a dead worker; or the error, again, here
                log.warning("decomposing in a worker failed (%s); decomposing here",
                            one_line(exc))
                decomposition = self._decomposition().fit(points)
            if begun[2] is not None:
                embedded = begun[2].stop(collect=True)
                if begun[2].params == self._embed_params():
                    ahead = embedded
                log.info("%d of %d charts embedded ahead%s", len(embedded),
                         decomposition.n_charts_, "" if ahead is embedded else " with another K")
        self.timings_["charts"] = time.perf_counter() - started
        self.decomposition_ = decomposition
        self.points_ = points
        fitted, self.faults_ = fit_every_chart(
            decomposition, points, workers, self._embed_params(), self.hidden_layers,
            self.reuse_layers, self.max_splits, ahead, started,
            search=dict(max_layers=self.max_layers, max_neurons=self.max_neurons))
        return points, fitted

    def _embed_params(self) -> dict:
        """`chart_fit.embed_chart`'s parameters of this atlas's charts."""
        return dict(lam=self.lam, depth=self.depth, random_state=self.random_state,
                    n_neighbors=self.n_neighbors)

    def _join(self, decide: bool = True, fresh=None) -> None:
        """Join the charts' parts into ``mesh_``. ``decide``: find again which side of each
        chart is outside and whether the cloud is closed (`fit`); `remesh` keeps the fit's.
        ``fresh`` (c,) bool: the charts meshed anew (None: all), whose parts are taken again."""
        started = time.perf_counter()
        parts = self._chart_parts(fresh)
        voxel = self.voxel * self.decomposition_.spacing_
        reach = self.reach * self.decomposition_.spacing_
        chart_samples_ = [part.samples for part in parts]
        unturned = [part.normals for part in parts]
        chart_normals = [s * n for n, s in zip(unturned, self.signs_, strict=True)]
        if decide or not hasattr(self, "shells_"):
            two_layer = (None if self.closed is False else two_layer_charts(
                [self._chart_mesh(i) for i in range(len(parts))], self.chart_points_,
                self.points_, voxel))
            sides = ChartSides(band=self.band, closed=self.closed).fit(
                chart_samples_, chart_normals, self.points_, self.decomposition_.spacing_,
                voxel, self.chart_points_, two_layer, layered=self._layered_charts,
                reach=self._uncharted_reach())
            self.closed_, self.seal_, self.votes_ = sides.closed_, sides.seal_, sides.votes_
            if sides.layered_ is not None:
                warnings.warn(
                    f"joined closed, with thin shells: charts holding {sides.layered_:.0%} of "
                    f"the samples are seen from both sides with their points in two layers "
                    f"(walls thinner than the noise); closed=False (--closed no) joins it open",
                    ReconstructionWarning, stacklevel=3)
            if sides.mixed_ is not None:
                warnings.warn(
                    f"joined open, but charts holding {sides.mixed_[0]:.0%} of the samples face "
                    f"out of a volume and {sides.mixed_[1]:.0%} are seen from both sides: if "
                    f"the object is closed, its walls are thinner than the noise or were seen "
                    f"from one side only (a scan's unseen inside), and closed=True "
                    f"(--closed yes) joins them as thin shells",
                    ReconstructionWarning, stacklevel=3)
            if sides.open_pieces_ is not None:
                warnings.warn(
                    f"joined closed, but charts holding {sides.open_pieces_:.0%} of the samples, "
                    f"apart from the rest, are seen from both sides: an open surface there is "
                    f"joined as a thin closed shell; closed=False (--closed no) joins the whole "
                    f"cloud open, or reconstruct that part on its own",
                    ReconstructionWarning, stacklevel=3)
            self.shells_, self.thin_ = sides.shells_, sides.thin_
            self.signs_ = self.signs_ * sides.turns_
            self._probe = sides.probe_
            chart_normals = [s * n for n, s in zip(unturned, self.signs_, strict=True)]
        chart_samples_ = self._detailed_samples(parts)  # (the sides decided on the charts' own)
        if self.closed_:  # a flap of a chart folded over an edge faces in: turn it out
            probe = self._exterior_probe(chart_samples_, voxel)
            inward = np.split(probe.facing_in(np.concatenate(chart_samples_),  # all at once
                                              np.concatenate(chart_normals)),
                              np.cumsum([len(s) for s in chart_samples_])[:-1])
            chart_normals = [np.where(turn[:, None], -n, n)
                             for turn, n in zip(inward, chart_normals, strict=True)]
        else:  # an open join trims its mesh to its samples: no slits
            self._fill_stretched(parts, chart_samples_, chart_normals, reach)
        samples, normals, kept_open = [], [], []
        for s, n, shell, far_face in zip(chart_samples_, chart_normals, self.shells_,
                                         self.thin_, strict=True):
            if shell:  # a part thinner than the noise, charted once: a thin closed shell
                s, n = thin_shell(s, n, self.shell * voxel)
            samples.append(s)
            normals.append(n)
            kept_open.append(np.full(len(s), bool(far_face)))  # both faces of its shell
        samples, normals = np.concatenate(samples), np.concatenate(normals)
        kept_open = np.concatenate(kept_open)
        uncharted = ((lambda tree, moved: self._uncharted_tracker()(samples, tree, moved))
                     if self.closed_ else None)
        kept_open = kept_open if kept_open.any() else None

        def join(grid):
            return implicit_mesh(samples, normals, voxel, band=self.band, trim=self.trim,
                                 closed=self.closed_, seal=self.seal_, uncharted=uncharted,
                                 grid=grid, kept_open=kept_open), grid
        self.mesh_, _ = join(self._join_grid(voxel))
        if decide and self.closed_:  # a topology that depends on where the grid falls
            self.mesh_, self._sdf, _, note = steady_join(
                self.mesh_, self._sdf, lambda shift: join(ClosedSDF(voxel, shift=shift)))
            if note:  # (the advice: `reconstruct.join_alignment`)
                larger = float(f"{LARGER_VOXEL * self.voxel:.2g}")
                warnings.warn(f"{note}; where the samples are uneven, a larger voxel may steady "
                              f"it (voxel={larger:g}, --voxel {larger:g}; now {self.voxel:g} "
                              f"median spacings), at some cost in thin detail",
                              ReconstructionWarning, stacklevel=3)
        if decide:
            self.__dict__.pop("_seen_side", None)
        if not self.closed_ and self.up is not None:
            self._face_seen_side()
        self.samples_, self.normals_ = samples, normals
        self._joined_up = self._up_key()
        if decide or not (self._sdf.hit_ and hasattr(self, "euler_")):  # else the same mesh
            self.watertight_, self.winding_consistent_, self.euler_ = (
                kept_topology(self._sdf, self.mesh_.faces) or topology(self.mesh_.faces))
        if self.closed_ and not self.watertight_:
            warnings.warn("the cloud looks closed (its charts face out of one volume) but the "
                          "joined mesh is not watertight", ReconstructionWarning, stacklevel=3)
        self.timings_["join"] = time.perf_counter() - started

    def _layered_charts(self) -> np.ndarray:
        """(c,) bool: the charts whose points lie in two layers about their mesh
        (`faithfulness.LAYERED_KURTOSIS`), from the residuals their fields found at fit (an
        atlas saved before them: found again)."""
        details = self.__dict__.get("details_")
        if details is not None:
            return np.array([sampled_kurtosis(d.residuals_) < LAYERED_KURTOSIS
                             for d in details])
        return np.array([residual_kurtosis(self._chart_mesh(i), self.points_[np.asarray(m)])
                         < LAYERED_KURTOSIS for i, m in enumerate(self.chart_points_)])

    def _uncharted_tracker(self) -> UnchartedTracker:
        """The closed join's `UnchartedTracker` of the charted points, kept between re-meshes."""
        tracker = self.__dict__.get("_tracker")
        spacing, reach = self.decomposition_.spacing_, self._uncharted_reach()
        if (tracker is None or tracker.points is not self.points_ or tracker.spacing != spacing
                or tracker.reach != reach):
            tracker = self._tracker = UnchartedTracker(self.points_, spacing, reach)
        return tracker

    def _uncharted_reach(self) -> float:
        """How far from every joined sample a point is one the charts left out
        (`chart_sides.uncharted_reach` of the spacing and ``noise_``; a state saved before the
        noise was measured: the spacing's, as it was fitted)."""
        return uncharted_reach(self.decomposition_.spacing_, self.__dict__.get("noise_"))

    def _exterior_probe(self, chart_samples_, voxel: float) -> ExteriorProbe:
        """The `ExteriorProbe` the charts' sides were decided with, kept for re-meshing (a
        re-mesh moves few samples of a closed join); a loaded atlas builds it once again
        from its samples and the data they leave out (0.3 s)."""
        if "_probe" not in self.__dict__:
            everything = np.concatenate([s for s in chart_samples_ if len(s)])
            self._probe = ExteriorProbe(everything, voxel, self.seal_, uncharted_points(
                self.points_, everything, self.decomposition_.spacing_,
                reach=self._uncharted_reach()))
        return self._probe

    def _face_seen_side(self) -> None:
        """Turn the open ``mesh_`` to face the side the cloud was seen from
        (`join.faces_seen_side`), found when the charts' sides are decided (or ``up``
        changed) and kept: a re-mesh does not turn the mesh over between two λ."""
        key = tuple(float(x) for x in check_up(self.up))
        kept = self.__dict__.get("_seen_side")
        if kept is None or kept[0] != key:
            kept = self._seen_side = (key, faces_seen_side(self.mesh_.vertices,
                                                            self.mesh_.faces, self.points_,
                                                            self.up))
        if not kept[1]:
            turn_faces(self.mesh_)

    def _chart_parts(self, fresh=None) -> list[ChartPart]:
        """Each chart's `ChartPart`: kept from the last join, or taken again from its mesh when
        it has none or is ``fresh`` ((c,) bool; None: every chart that has a mesh)."""
        if "_owners" not in self.__dict__:  # kept for re-meshing (a fit drops it)
            self._owners = self._chart_owners()
        parts = self.__dict__.get("_parts")
        if parts is None or len(parts) != len(self.charts_):
            parts = [None] * len(self.charts_)
        todo = [i for i, (chart, part) in enumerate(zip(self.charts_, parts, strict=True))
                if part is None or (fresh[i] if fresh is not None else "mesh_" in vars(chart))]
        if todo:
            for i in todo:
                self._chart_mesh(i)  # (meshed again if a re-mesh skipped it)
            taken = parts_of([self.charts_[i] for i in todo], todo, self._owners,
                             self.reach * self.decomposition_.spacing_)
            for i, part in zip(todo, taken, strict=True):
                parts[i] = part
        self._parts = parts
        return parts

    def _detailed_samples(self, parts) -> list[np.ndarray]:
        """Each chart's part's samples with the shape its network left in its residuals put
        back (`residual_detail`); not a thin shell's (``shells_``: its points lie on both faces
        of a part thinner than the noise, whose mean is no shape: the sheets at σ 0.5 %, 20k,
        seeds 1 / 2, Chamfer 0.396 / 0.378 without the fields, 0.431 / 0.403 with them there)."""
        return [part.samples if shell else self._detailed(i, "samples", part.samples,
                                                          part.normals)
                for i, (part, shell) in enumerate(zip(parts, self.shells_, strict=True))]

    def _detailed(self, index: int, kind: str, samples, normals) -> np.ndarray:
        """``samples`` (q, 3) of chart ``index``'s part (``kind``: its vertices or the extra
        samples on its faces) moved by its `ResidualDetail` along their ``normals``, kept while
        the part keeps them; as they are for an atlas without (saved before it was built)."""
        details = self.__dict__.get("details_")
        if details is None:
            return samples
        kept = self.__dict__.setdefault("_detail_kept", {})
        held = kept.get((index, kind))
        if held is None or held[0] is not samples:
            detail = details[index]
            offsets = detail.offsets(samples, known=None if held is None else held[:2])
            held = kept[index, kind] = (samples, offsets,
                                        detail.moved(samples, normals, offsets))
        return held[2]

    def _chart_mesh(self, index: int) -> trimesh.Trimesh:
        """Chart ``index``'s mesh, meshed again if a re-mesh skipped it."""
        chart = self.charts_[index]
        if "mesh_" not in vars(chart):
            with chart_steps():
                chart.remesh()
        return chart.mesh_

    def _fill_stretched(self, parts, chart_samples_, chart_normals, reach):
        """Add to each chart's samples and normals (lists, in place) those on its faces that
        its map stretches and on its faces across the border with another chart's part
        (`join.stretched_samples`), lying in its own part of the cloud, as its vertices must;
        found once per chart mesh (kept in its part)."""
        todo = [i for i, part in enumerate(parts) if part.extra is None]
        skipped = [i for i in todo if "mesh_" not in vars(self.charts_[i])]
        if skipped:  # joined closed since: meshed again, their parts (the same) indexed anew
            self._chart_parts([i in skipped for i in range(len(parts))])
        if todo:
            meshes = [self.charts_[i].mesh_ for i in todo]
            kept = [parts[i].kept for i in todo]
            labels, tree = self._owners
            border = [border_vertices(mesh, k) for mesh, k in zip(meshes, kept, strict=True)]
            theirs = owned([mesh.vertices[b] for mesh, b in zip(meshes, border, strict=True)],
                           labels, tree, reach, charts=todo, others=True)
            filled = stretched_samples(meshes, kept, [parts[i].normals for i in todo],
                                       STRETCHED, [b[t] for b, t in zip(border, theirs,
                                                                        strict=True)])
            mine = owned([extra for extra, _ in filled], labels, tree, reach, charts=todo)
            for i, (extra, extra_normals), own in zip(todo, filled, mine, strict=True):
                parts[i].extra, parts[i].extra_normals = extra[own], extra_normals[own]
        for i, part in enumerate(parts):
            if len(part.extra):
                extra = (part.extra if self.shells_[i] else
                         self._detailed(i, "extra", part.extra, part.extra_normals))
                chart_samples_[i] = np.concatenate([chart_samples_[i], extra])
                chart_normals[i] = np.concatenate([chart_normals[i],
                                                   self.signs_[i] * part.extra_normals])

    def _join_grid(self, voxel: float) -> SparseSDF | ClosedSDF:
        """The join's grid kept between re-meshes (`implicit_mesh`): of the closed kind for a
        closed cloud."""
        kind = ClosedSDF if self.closed_ else SparseSDF
        if not isinstance(self.__dict__.get("_sdf"), kind):
            self._sdf = kind(voxel)
        return self._sdf

    def _chart_owners(self):
        """(n,) the chart (index into ``charts_``) of each input point, −1 where its chart did
        not fit, and a `kdtree.PointTree` of the points that have one."""
        lookup = np.full(int(self.decomposition_.labels_.max(initial=-1)) + 2, -1)
        lookup[np.asarray(self._chart_ids, int)] = np.arange(len(self._chart_ids))
        labels = lookup[self.decomposition_.labels_]  # label −1 reads the last entry, −1
        return labels, PointTree(self.points_[labels >= 0])

    def remesh(self, **params) -> trimesh.Trimesh:
        """Re-mesh every chart with new ``lam``, ``depth``, ... through its ONNX map (no
        retraining) and join them again. Returns and stores ``mesh_``.

        Each chart keeps the grid spacing it was fitted with (`fit` sets its ``grid_spacing``),
        and its grid lies on the lattice of that spacing, so a new outline moves only the
        vertices near it. A chart whose part of the join cannot change with its new outline
        (`chart_parts.unchanged`: its outline moves in the overlap rings, away from its own part
        of the cloud) takes the parameters but is not meshed (its ``mesh_`` is dropped); when
        no chart was, the mesh stands. The join re-evaluates its grid only round the samples
        that moved (`SparseSDF.update`, `ClosedSDF.update` when closed) and gives back the same
        mesh when none of its samples did. Torus 22k, 37 charts, 44,600 vertices: a new λ or
        depth meshes 0-1 charts (the figurine 13-19 of 37; a mug's or an open surface's charts
        mostly own part of their outlines, and are all meshed). A chart whose boundary cannot
        take the parameters keeps its own (one warning); when no chart can, the error is
        raised and the atlas is as it was (`reconstruct.atlas_remesh`)."""
        if not hasattr(self, "charts_"):
            raise NotFittedError("fit() the atlas first")
        return remesh_atlas(self, params)

    def _up_key(self):
        """What of ``up`` an open join's mesh depends on (`_face_seen_side`)."""
        if self.closed_ or self.up is None:
            return None
        return tuple(float(x) for x in check_up(self.up))

    # -- persistence ---------------------------------------------------------------------------
    def state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """The fitted state as (meta, arrays): what re-meshing needs, and no network
        (`reconstruct.atlas_state.atlas_state`)."""
        return atlas_state(self)

    @classmethod
    def from_state(cls, meta: dict, arrays: dict) -> AtlasReconstructor:
        """Rebuild a fitted atlas from `state`; it can `remesh()` at once (no torch needed;
        `reconstruct.atlas_state.atlas_from_state`)."""
        return atlas_from_state(cls, meta, arrays)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the fitted state (`state`) atomically to an .npz file."""
        return write_state(path, *self.state())

    @classmethod
    def load(cls, path: str | os.PathLike) -> AtlasReconstructor:
        """Read an atlas written by `save` (or by `SurfaceReconstructor.save` of an atlas).
        A damaged or foreign file raises `InvalidInputError` in one line."""
        meta, arrays = read_state(path)
        if meta.get("format") != ATLAS_FORMAT:
            raise InvalidInputError(
                f"{path}: not an atlas state (format {meta.get('format')!r})")
        try:
            return cls.from_state(meta, arrays)
        except Exception as exc:  # a missing array, a bad header field, a broken ONNX model
            raise InvalidInputError(
                f"{path}: damaged atlas state ({one_line(exc)})") from exc
