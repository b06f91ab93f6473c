"""The whole method in one estimator: embed → adaptive MLP → boundary → spline → mesh → 3D.

A fitted reconstruction keeps the embedded points and the ONNX surface map, so `remesh` with a
new λ, boundary depth or grid spacing runs in milliseconds without retraining, and `save` /
`load` carry that state to another process (of an atlas: every chart's,
`AtlasReconstructor.state`). ``fit(points, warm_start=earlier)`` fits the same surface again
after more points arrived: the new embedding is aligned to the earlier one
(`reconstruct.alignment`) and the earlier network fine-tuned, with no architecture search.
"""

from __future__ import annotations

import copy
import logging
import os
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from sklearn.base import BaseEstimator, clone

from .alignment import align_to
from .boundary import MultiDepthBoundary, PCABoundary, boundary_geometry
from .charts import MIN_CHART_POINTS
from .embedding import SurfaceEmbedding
from .errors import (
    CloudInPiecesError,
    FitError,
    InvalidInputError,
    NotFittedError,
    ReconstructionWarning,
    WarmStartRefused,
)
from .faithfulness import (
    APART_KURTOSIS,
    BRIDGE_LIMIT,
    LAYERED_KURTOSIS,
    MISSED_LIMIT,
    UNEXPLAINED_LIMIT,
    bridged_share,
    explained_distance,
    missed_region,
    neighbour_preservation,
    residual_kurtosis,
    unexplained_fraction,
    volume_warning,
)
from .io import one_line, read_state, write_state
from .join import check_up, faces_seen_side
from .kdtree import PointTree
from .meshing import default_spacing, lattice_grid, lattice_nodes, mesh_inside, sample_ring
from .mlp import AdaptiveMLP
from .outline import border_inset, border_spacing, extend_outline
from .pipeline_state import STATE_FORMAT, reconstruction_from_state, reconstruction_state
from .spline import BoundarySpline, SplineInput, spline_input
from .validation import (
    ATLAS_POINTS,
    check_max_points,
    check_points,
    check_voxel,
    random_subset,
)

log = logging.getLogger(__name__)

#: Default smoothing λ, chosen from bench/quality.py. The spline's s = λ · m · var where var is
#: the interpolants' jaggedness (`BoundarySpline(variance="local")`): λ = 1 is Dierckx's own
#: s ≈ m σ²; the paper's λ = 2.4 is of this order. The "global" reading (var = spread about the
#: centroid) either shrinks the boundary (λ ≥ 0.002) or lets the spline cross itself (smaller λ).
DEFAULT_LAM = 1.0
#: Default boundary depth: on bench/quality.py deeper paths trade completeness for robustness to
#: stray points; 2 keeps F-score ≥ 0.97 on the smooth shapes while still combining two paths.
DEFAULT_DEPTH = 2
#: One chart is not tried when the embedding's residual variance (1 − R² of geodesic against
#: embedded distances) is above this. Measured at 1,600 and 20,000 points, σ 0.5 % and 1 %:
#: every bench.quality shape ≤ 0.006; the closed awkward objects: hook 0.019–0.024, torus
#: 0.056–0.060, figurine 0.083–0.094, mug 0.33–0.41 (the two plates of `sheets`: 0.001, left to
#: the unexplained check). Neighbour preservation does not separate them at 20,000 points, σ 1 %
#: (discs 0.51–0.61, closed 0.28–0.41).
ATLAS_RESIDUAL = 0.015
ATLAS_MODES = ("auto", "never", "always")
#: A denser ``atlas="auto"`` cloud is first embedded on a random this many of its points (the
#: atlas's own ``max_points``): when their residual variance is over `GLANCE_MARGIN` times
#: `ATLAS_RESIDUAL`, the atlas is fitted without embedding the cloud (its `MAX_POINTS`),
#: whose embedding only decided that. 100,000 points at σ 0.5 %, the whole cloud's residual
#: against three draws of 20,000: every bench.quality shape within 0.001 (all ≤ 0.0053), mug 0.353 /
#: 0.359-0.361, chair 0.083 / 0.063-0.074, hook 0.020 / 0.018-0.021 (left to the whole
#: cloud's, as are all near the limit); the embedding took 14-31 s of 100,000 points, 2.2-4.3 s
#: of 20,000. A 300,000-point mug took 87 s, 70 of them embedding the whole cloud (before
#: `MAX_POINTS`).
GLANCE_POINTS = 20000
GLANCE_MARGIN = 3.0
#: A denser cloud is fitted on a random this many of its points (``max_points``): its net trains
#: on at most 18,000 of them (`AdaptiveMLP`: three bags of 6,000), and embedding every point
#: costs as its graph grows (`scanstation reconstruct` of a 300,000-point terrain: 102 s and
#: 2.3 GB, about 70 s of it embedding; now 19 s and 0.74 GB).
#: bench.quality's shapes at 100,000 points, σ 0.5 %, seeds 0 / 1, Chamfer-L1 fitted on all /
#: on 40,000: s_curve 0.00155 / 0.00151, 0.00139 / 0.00130; torus_quarter 0.00062 / 0.00077;
#: torus_half 0.00178 / 0.00159, 0.00168 / 0.00206; sparse_cone 0.00035 / 0.00031;
#: sphere_cap 0.00072 / 0.00071; saddle 0.00074 / 0.00097; terrain 0.00065 / 0.00069, F
#: 0.9999-1.0 all; 17-35 s against 10-17 s. On 20,000 they were worse (torus_quarter 0.00088,
#: saddle 0.00095, s_curve 0.00189: the net's bags overlap).
MAX_POINTS = 40_000
#: From this many points, an ``atlas="auto"`` fit starts chart workers on a spare core as it
#: begins (`AtlasReconstructor.warm`: they import torch while it embeds), then decomposes the
#: cloud for an atlas there while it searches one chart's net (`AtlasReconstructor.start`), in
#: case the searched mesh shows that one chart cannot hold it. Rough 20k: the 2.1 s
#: decomposition is then hidden. When one chart serves, the idle workers train some of its final
#: fits (`AdaptiveMLP.finish`).
SPECULATE_FROM = 10000
#: `AdaptiveMLP.weight_decay` of a one-chart fit's final fits. bench.quality at 1,600 points,
#: seeds 0-5 against the search before issue 17 (bench.compare_quality: geometric mean of the
#: paired Chamfer-L1 ratios): 0.952 without, cases over 2 % worse 6 of 14; 0.921 with 0.01,
#: 1 of 14 (the dense cone at σ 1 %, 1.028). Clouds of more than about 3,200 points train
#: without it (`mlp.DECAY_UP_TO`), as do an atlas's charts (not measured there).
FINAL_WEIGHT_DECAY = 0.01
_MESH_PARAMS = ("lam", "depth", "n_corners", "boundary", "grid_spacing", "variance", "extend")
#: Training-only parameters: not saved (a loaded reconstruction re-meshes, it does not train;
#: an atlas's ``closed`` and ``voxel`` are in its own state).
_TRAINING_PARAMS = ("mlp", "fine_tune", "warm_tolerance", "atlas", "max_points", "closed",
                    "voxel", "atlas_points")


def _check_known(params: dict) -> None:
    unknown = set(params) - set(_MESH_PARAMS)
    if unknown:
        raise InvalidInputError(f"cannot re-mesh with {sorted(unknown)}: not a mesh parameter")


class Embedded(NamedTuple):
    """What `SurfaceReconstructor.embed` computes of a cloud before any network, for
    ``fit(points, embedded=...)`` to take up: the same fit, its first steps done ahead (an atlas
    embeds its charts on an idle core while a one-chart fit searches)."""

    points: np.ndarray  # (m, 3) the cloud embedded (at most ``max_points`` of it)
    embedding: SurfaceEmbedding  # fitted on it
    boundaries: dict  # its boundary samples at the depths asked (the fit's boundary cache)
    key: tuple  # the parameters they depend on (`SurfaceReconstructor._embedding_key`)


class SurfaceReconstructor(BaseEstimator):
    """Reconstruct a triangle mesh from a noisy point cloud (White & Bai; Yumer & Kara).

    Parameters
    ----------
    lam : spline smoothing λ; larger gives a smoother boundary.
    variance : the variance in the spline's s = λ · m · var: "local" (the interpolants'
        jaggedness; λ ≈ 1) or "global" (their spread about the centroid, the paper's literal
        rule; λ ≈ 0.001–0.01). See `reconstruct.spline`.
    depth : number of boundary path depths sampled (the paper's multi-depth method).
    n_corners : corners of the boundary paths (>= 8).
    boundary : "multidepth" (the paper) or "pca" (the Yumer–Kara baseline).
    embedding : "auto", "isomap", "mlle" or "landmark".
    n_neighbors : K of the neighbourhood graph; None chooses it automatically.
    max_layers, max_neurons, activation, retrain : the adaptive MLP search (`AdaptiveMLP`).
    grid_spacing : spacing of the interior grid in embedding units; None derives it from density.
        Given, the grid lies on the lattice of that spacing: a new λ or depth moves only the
        vertices near the outline.
    extend : grow the spline polygon outward before meshing, in local point spacings
        (`reconstruct.outline`): "auto" brings a multi-depth boundary out to where a 1-deep loop
        through the outermost samples lies (the deeper loops' extra inset), the furthest the
        network has data; "border" out to the sampled region's estimated true border (more
        complete, but the network extrapolates there); a number; 0 meshes the spline as fitted.
    random_state : seed; the same seed gives the same mesh.
    atlas : "auto" fits an atlas of charts (`reconstruct.atlas`) instead of one chart when the
        cloud is not one disc-like surface: its embedding's residual variance is over
        ``ATLAS_RESIDUAL``, the one-chart mesh leaves more than ``UNEXPLAINED_LIMIT`` of the
        points unexplained, or more than ``BRIDGE_LIMIT`` of its area spans holes in the data
        (`faithfulness.bridged_share`; the atlas then fits the piece the chart fitted).
        From ``SPECULATE_FROM`` points it decomposes the cloud for the atlas in a worker
        process while the one chart is searched (stopped if one chart holds the cloud);
        "never" keeps one chart (and warns); "always" fits an atlas.
    closed, voxel, atlas_points : an atlas's (`AtlasReconstructor`): None decides whether the
        cloud is closed, True joins it as the boundary of a volume, False as an open surface;
        the grid spacing of its join in median point spacings; how many points of a denser
        cloud it charts (its ``max_points``, `validation.ATLAS_POINTS`; None: all; at most
        ``max_points``, the points a fit takes).
    mlp : an unfitted `AdaptiveMLP` (cloned by `fit`) used instead of the one ``max_layers``,
        ``max_neurons``, ``activation``, ``retrain`` and ``random_state`` describe: other
        training budgets, or ``hidden_layers`` to skip the search.
    fine_tune : `AdaptiveMLP` parameters set on a warm start's network before it is fine-tuned
        (e.g. ``{"final_epochs": 300, "patience": 12}``; None: as the earlier fit had them).
    warm_tolerance : distance (input units) within which a point counts as one a warm start's
        earlier fit saw; None: the earlier points' median nearest-neighbour spacing.
    up : (3,) the direction the surface is seen from above: an open mesh is turned to face
        from above and around, as a scan station or a scanner over a table sees it
        (`join.faces_seen_side`, found once per map; a network's map leaves the side free);
        None: as the map gives it (an atlas's charts and a scan's sectors, whose owners orient
        them).
    max_points : a denser cloud is fitted on a random this many of its points (`MAX_POINTS`;
        None: on all), and its mesh has about as many vertices (a smaller ``grid_spacing``
        re-meshes it finer); ``points_`` and ``unexplained_`` are then of those.

    Fitted attributes: ``embedding_`` (m, 2), ``points_`` (m, 3) the points it was fitted to,
    ``mlp_`` (`AdaptiveMLP`; not after `load`), ``embedding_method_``, ``n_neighbors_``,
    ``surface_map_`` (OnnxSurfaceMap), ``hidden_layers_``, ``mesh_`` (trimesh.Trimesh),
    ``boundary_points_`` (k, 2), ``spline_`` (BoundarySpline), ``vertices_2d_`` (v, 2),
    ``unexplained_`` share of the points (the outliers aside, those of every piece of the
    neighbourhood graph, though only the largest is fitted) the mesh leaves farther than their
    noise allows and
    ``neighbour_preservation_`` of the embedding (`reconstruct.faithfulness`; a
    `ReconstructionWarning` when the share is over 5 %), ``missed_region_`` (share, centre (3,))
    the largest patch of unexplained points when there are 1-5 % (`faithfulness.missed_region`;
    a warning when over 1 %: a region the mesh misses), ``residual_kurtosis_`` of the points'
    signed distances to the one chart's mesh (about 3; under 2.5 a warning, two layers; under
    `faithfulness.APART_KURTOSIS`, layers apart, an atlas).
    ``timings_`` (seconds per stage of the last fit / remesh: embedding, search, final fits,
    export, boundary, mesh).
    When an atlas was fitted: ``atlas_`` (`AtlasReconstructor`), ``atlas_reason_`` (why), and
    ``mesh_``, ``unexplained_``, ``neighbour_preservation_``, ``missed_region_`` (of all the
    points given) are the atlas's; the one-chart
    attributes (``embedding_``, ``surface_map_``, ...) are not set.
    """

    #: A chart of an atlas (set by `reconstruct.chart_fit`): whether its points fill a volume is
    #: the atlas's to say, once for the cloud (`faithfulness.volume_warning`, 35 ms a chart).
    _atlas_chart = False

    def __init__(
        self,
        lam: float = DEFAULT_LAM,
        depth: int = DEFAULT_DEPTH,
        n_corners: int = 8,
        boundary: str = "multidepth",
        embedding: str = "auto",
        n_neighbors: int | None = None,
        max_layers: int = 2,
        max_neurons: int = 20,
        activation: str = "tanh",
        retrain: bool = False,
        grid_spacing: float | None = None,
        random_state: int | None = 0,
        variance: str = "local",
        extend: float | str = "auto",
        mlp=None,
        fine_tune: dict | None = None,
        warm_tolerance: float | None = None,
        atlas: str = "auto",
        up: tuple[float, float, float] | None = (0.0, 0.0, 1.0),
        max_points: int | None = MAX_POINTS,
        closed: bool | None = None,
        voxel: float = 0.5,
        atlas_points: int | None = ATLAS_POINTS,
    ):
        self.lam = lam
        self.depth = depth
        self.n_corners = n_corners
        self.boundary = boundary
        self.embedding = embedding
        self.n_neighbors = n_neighbors
        self.max_layers = max_layers
        self.max_neurons = max_neurons
        self.activation = activation
        self.retrain = retrain
        self.grid_spacing = grid_spacing
        self.random_state = random_state
        self.variance = variance
        self.extend = extend
        self.mlp = mlp
        self.fine_tune = fine_tune
        self.warm_tolerance = warm_tolerance
        self.atlas = atlas
        self.up = up
        self.max_points = max_points
        self.closed = closed
        self.voxel = voxel
        self.atlas_points = atlas_points

    def fit(self, points, warm_start: SurfaceReconstructor | None = None,
            embedded: Embedded | None = None) -> SurfaceReconstructor:
        """points : (n, 3) float, any unit. Returns self with ``mesh_`` set.

        warm_start : a fitted reconstruction of the same surface (e.g. from fewer points). Its
            neighbourhood size is reused, the new embedding aligned to its embedding and its
            network fine-tuned (``fine_tune``); raises `WarmStartRefused` (nothing changed)
            when too few points are shared, the embeddings disagree or it has no network.
        embedded : `embed`'s of these points with these parameters: its embedding and
            boundary samples are taken instead of computed (the same mesh)."""
        self._check_mesh_params()
        self._check_fit_params()
        points = self._drawn(np.array(check_points(points)))  # own: ``points_`` may be it
        if embedded is not None:
            self._check_embedded(embedded, points, warm_start)
        for name in ("atlas_", "atlas_reason_"):
            self.__dict__.pop(name, None)
        self.timings_ = {}
        self._given = points  # (an atlas's mesh is checked against all of them)
        spare = None  # chart workers warmed on the spare cores, in case one chart cannot serve
        try:
            if self.atlas == "always" and warm_start is None:
                return self._fit_atlas(points, "asked for")
            started = time.perf_counter()
            if warm_start is None and self.atlas == "auto" and len(points) >= SPECULATE_FROM:
                spare = self._new_atlas()
                spare.warm()
            return self._fit_from_scratch(points, warm_start, spare, started, embedded)
        finally:
            self.__dict__.pop("_given", None)
            if spare is not None:
                spare.cancel()  # nothing, when the atlas took it up

    def _check_fit_params(self) -> None:
        """The fit's own parameters, checked before any work: a cloud that goes straight to
        the atlas never reaches the search that checks its limits (``max_layers=0`` was taken
        without a word)."""
        if self.atlas not in ATLAS_MODES:
            raise InvalidInputError(f"atlas must be one of {ATLAS_MODES}, got {self.atlas!r}")
        if not (self.closed is None or isinstance(self.closed, bool)):
            raise InvalidInputError(f"closed must be None, True or False, got {self.closed!r}")
        check_voxel(self.voxel)
        check_max_points(self.max_points)
        check_max_points(self.atlas_points, "atlas_points")
        # an atlas_points asked above what a fit takes: not taken without a word (the
        # default's is: a fit of max_points=300 charts its 300)
        if self.max_points is not None and self.atlas_points != ATLAS_POINTS and (
                self.atlas_points is None or self.atlas_points > self.max_points):
            raise InvalidInputError(
                f"atlas_points {self.atlas_points or 'None (all)'} is above max_points "
                f"{self.max_points}: an atlas charts the points a fit takes (raise max_points "
                f"too; None takes all, --max-points all)")
        self._new_mlp()._check_params()  # its search limits, as the search would check them
        seed = self.random_state
        if isinstance(seed, (int, np.integer)) and seed < 0:
            raise InvalidInputError(f"random_state (the seed) must be >= 0, got {seed}")

    def embed(self, points, depths=()) -> Embedded:
        """The start of `fit` that needs no network: embed ``points`` (n, 3) (those `fit`
        takes: a random ``max_points`` of a denser cloud) and sample their boundary at each of
        ``depths``, for ``fit(points, embedded=...)``."""
        points = self._drawn(np.array(check_points(points)))
        embedding = self._embedding_estimator(self.n_neighbors).fit(points)
        sampler = copy.copy(self)  # samples with this one's parameters, into a cache of its own
        sampler.__dict__.update(embedding_=embedding.embedding_, _boundary_cache={})
        sampler.sample_boundaries(depths)
        return Embedded(points, embedding, sampler._boundary_cache, self._embedding_key())

    def _drawn(self, points: np.ndarray) -> np.ndarray:
        """The points (m, 3) fitted: all, or a random ``max_points`` of denser ``points``."""
        drawn = random_subset(points, self.max_points, self.random_state)
        if len(drawn) < len(points):
            log.info("fitting %d of the %d points (max_points)", len(drawn), len(points))
        return drawn

    def _embedding_key(self) -> tuple:
        return (self.embedding, self.n_neighbors, self.random_state, self.boundary,
                self.n_corners)

    def _embedding_estimator(self, n_neighbors, may_chart: bool = False) -> SurfaceEmbedding:
        """The embedding step; one that ``may_chart`` (an atlas may follow) refuses a cloud
        whose graph's pieces other than the largest, of an atlas chart's points at least
        (`MIN_CHART_POINTS`: it leaves smaller ones out too), hold over `MISSED_LIMIT` of it
        (several objects: one chart of the largest would leave them out, and three of a third
        each were refused outright) with `CloudInPiecesError`."""
        return SurfaceEmbedding(method=self.embedding, n_neighbors=n_neighbors,
                                other_pieces=MISSED_LIMIT if may_chart else 0.5,
                                min_piece=MIN_CHART_POINTS if may_chart else 1,
                                random_state=self.random_state)

    def _check_embedded(self, embedded: Embedded, points, warm_start) -> None:
        if warm_start is not None:
            raise InvalidInputError("a warm start aligns an embedding of its own: give it or "
                                    "embedded, not both")
        if embedded.key != self._embedding_key() or not np.array_equal(embedded.points, points):
            raise InvalidInputError("embedded is of other points or other embedding or "
                                    "boundary parameters")

    def _fit_from_scratch(self, points, warm_start, spare, started, embedded=None):
        """`fit` from the embedding on (``spare``: an `AtlasReconstructor` whose workers
        `warm` started, or None; ``embedded``: `embed`'s, checked)."""
        n_neighbors = self.n_neighbors
        if warm_start is not None:
            if not hasattr(warm_start, "mlp_"):
                raise WarmStartRefused("the earlier fit has no network (loaded from disk)")
            n_neighbors = warm_start.n_neighbors_ if n_neighbors is None else n_neighbors
        may_chart = embedded is None and warm_start is None and self.atlas == "auto"
        if may_chart:
            reason = self._atlas_at_a_glance(points, n_neighbors)
            if reason is not None:
                self.timings_["embedding"] = time.perf_counter() - started
                return self._fit_atlas(points, reason, atlas=spare)
        if embedded is None:
            try:
                embedding = self._embedding_estimator(n_neighbors, may_chart).fit(points)
            except CloudInPiecesError as exc:
                if not may_chart:
                    raise
                self.timings_["embedding"] = time.perf_counter() - started
                return self._fit_atlas(points, _in_pieces(exc), atlas=spare)
            boundaries = {}
        else:
            embedding, boundaries = embedded.embedding, dict(embedded.boundaries)
        self.timings_["embedding"] = time.perf_counter() - started
        # the same array when the embedding kept every point: an atlas begun on it serves
        # whichever of the two `_atlas_reason` gives
        fitted = points if embedding.support_.all() else points[embedding.support_]
        uv = embedding.embedding_
        if warm_start is None and self.atlas == "auto":
            residual = embedding.residual_variance_
            if residual > ATLAS_RESIDUAL:
                return self._fit_atlas(points, (
                    f"its embedding's residual variance is {residual:.3f} (one disc-like "
                    f"surface: under {ATLAS_RESIDUAL})"), atlas=spare)
        self.embedding_ = uv
        self.points_ = fitted
        self._boundary_cache = boundaries
        self.__dict__.pop("_seen_side", None)  # of an earlier fit's embedding
        if spare is not None:  # the cloud decomposed for an atlas while one chart is searched,
            # and its charts embedded with this K
            spare.set_params(n_neighbors=embedding.n_neighbors_).start(fitted)
        return self._fit_one_chart(points, fitted, uv, embedding, warm_start, spare, started)

    def _atlas_at_a_glance(self, points, n_neighbors) -> str | None:
        """Why a cloud of more than `GLANCE_POINTS` needs an atlas, seen on a random
        `GLANCE_POINTS` of its (n, 3) ``points``; None when that is not clear from them (the
        whole cloud's embedding decides)."""
        if len(points) <= GLANCE_POINTS:
            return None
        glanced = random_subset(points, GLANCE_POINTS, self.random_state)
        try:
            residual = self._embedding_estimator(n_neighbors, True).fit(
                glanced).residual_variance_
        except CloudInPiecesError as exc:
            return f"of {GLANCE_POINTS} of its points, {_in_pieces(exc)}"
        if residual <= GLANCE_MARGIN * ATLAS_RESIDUAL:
            log.debug("%d of the %d points embed with residual variance %.3f: embedding all",
                      GLANCE_POINTS, len(points), residual)
            return None
        return (f"the embedding of {GLANCE_POINTS} of its {len(points)} points has residual "
                f"variance {residual:.3f} (one disc-like surface: under {ATLAS_RESIDUAL})")

    def _fit_one_chart(self, points, fitted, uv, embedding, warm_start, spare, started):
        """The rest of `fit` once the cloud is embedded: search, final fits, mesh, checks;
        or the atlas (``spare``: begun by `AtlasReconstructor.warm` and `start`) when they say
        so."""
        explained = None  # the distance that explains a point: measured once, if early
        # Points of the graph's other pieces count: a cloud the embedding kept only the largest
        # piece of (a sector of a knot crossing it twice) is not explained by its mesh.
        assessed = points[embedding.inliers_]
        if warm_start is None:
            mlp = self._new_mlp().search(uv, fitted)
            if self.atlas == "auto" and mlp.hidden_layers is None:  # the searched net's mesh
                self.surface_map_ = mlp.surface_map_
                self.timings_.update(mlp.timings_)
                self.remesh()
                explained = explained_distance(fitted)
                reason = self._atlas_reason(
                    points, unexplained_fraction(self.mesh_, assessed, threshold=explained),
                    mlp.hidden_layers_, embedding.n_neighbors_, limit=2 * UNEXPLAINED_LIMIT)
                if reason is not None:  # plainly one chart cannot hold it: no final fits
                    return self._fit_atlas(*reason, atlas=spare)
            executor, n_workers = (None, 0) if spare is None else spare.idle_workers()
            mlp.finish(executor, n_workers)  # idle, the spare workers train final fits too
        else:
            uv = align_to(uv, fitted, warm_start.embedding_, warm_start.points_,
                          self._warm_tolerance(warm_start))
            self.embedding_ = uv
            mlp = copy.deepcopy(warm_start.mlp_).set_params(**(self.fine_tune or {}))
            mlp.fine_tune(uv, fitted)
        self.embedding_method_ = embedding.method_
        self.n_neighbors_ = embedding.n_neighbors_
        self.mlp_ = mlp
        self.surface_map_ = mlp.surface_map_
        self.hidden_layers_ = tuple(mlp.hidden_layers_)
        self.timings_.update(getattr(mlp, "timings_", {}))
        self.remesh()
        if explained is None:
            explained = explained_distance(fitted)
        self.unexplained_ = unexplained_fraction(self.mesh_, assessed, threshold=explained)
        # a region the mesh misses, under the limit: in one patch, where noise scatters them
        self.missed_region_ = (missed_region(self.mesh_, assessed, explained)
                               if MISSED_LIMIT < self.unexplained_ <= UNEXPLAINED_LIMIT
                               else (0.0, np.full(3, np.nan)))
        self.residual_kurtosis_ = residual_kurtosis(self.mesh_, self.points_)
        if warm_start is None and self.atlas == "auto":
            reason = self._atlas_reason(points, self.unexplained_, self.hidden_layers_,
                                        self.n_neighbors_, missed=self.missed_region_,
                                        kurtosis=self.residual_kurtosis_)
            if reason is not None:
                return self._fit_atlas(*reason, atlas=spare)
        self._check_faithful()
        log.info(
            "reconstructed %d points in %.1f s: %s, K=%d, layers %s, %d vertices, %d faces",
            len(points),
            time.perf_counter() - started,
            self.embedding_method_,
            self.n_neighbors_,
            self.hidden_layers_,
            len(self.mesh_.vertices),
            len(self.mesh_.faces),
        )
        return self

    def _atlas_reason(self, points, unexplained: float, layers: tuple[int, ...], k: int,
                      limit: float = UNEXPLAINED_LIMIT, missed=None,
                      kurtosis: float | None = None) -> tuple | None:
        """(points, reason, hidden layers, K) for `_fit_atlas` when ``mesh_``, one chart, is
        the wrong model of the input ``points`` (n, 3); None when it is not.

        It leaves more than ``limit`` of them ``unexplained``: the atlas fits them all and
        searches its own layers (these were searched for a surface folded onto itself). Or,
        after the final fits, it leaves one patch of them over `MISSED_LIMIT` of the cloud
        (``missed``: `faithfulness.missed_region`), a region its boundary cut off: the atlas
        fits them all with the chart's ``layers`` and ``k``. Or it spans holes in the data: a
        disc-like surface, and the atlas fits the piece the chart fitted with the chart's
        ``layers`` and ``k`` (same density, same K: rough 20k, 39 charts, 1.5 s of K choices
        saved). Before the final fits, on the searched net's mesh, twice the limit counts (the
        final fits explain more; the holes spanned are the outline's, the same): rough 20k turns
        to an atlas 6 s sooner."""
        if unexplained > limit:
            return points, "one chart leaves too many points unexplained", None, None
        if missed is not None and missed[0] > MISSED_LIMIT:  # a corner cut off: a disc
            where = _in_words(missed)
            return points, f"one chart's mesh misses a region of the data ({where})", layers, k
        if bridged_share(self.mesh_, self.points_) > BRIDGE_LIMIT:
            return self.points_, "one chart's mesh spans holes in the data", layers, k
        if kurtosis is not None and kurtosis < APART_KURTOSIS:  # a thin part's two faces
            return points, (f"its points lie in two layers apart, one each side of one "
                            f"chart's mesh (residual kurtosis {kurtosis:.2f}: the faces of a "
                            f"thin part, or two sheets)"), None, None
        return None

    def _new_atlas(self):
        """An unfitted `AtlasReconstructor` with this reconstruction's λ, depth, join, search
        limits and seed."""
        from .atlas import AtlasReconstructor

        return AtlasReconstructor(lam=self.lam, depth=self.depth, up=self.up,
                                  closed=self.closed, voxel=self.voxel,
                                  max_points=self.atlas_points,
                                  max_layers=self.max_layers, max_neurons=self.max_neurons,
                                  random_state=self.random_state)

    def _fit_atlas(self, points, reason: str, hidden_layers: tuple[int, ...] | None = None,
                   n_neighbors: int | None = None, atlas=None) -> SurfaceReconstructor:
        """Fit an atlas of charts (`reconstruct.atlas`; ``hidden_layers``: what a one-chart
        search chose; ``atlas``: one begun with `AtlasReconstructor.warm` or `start`) and take
        its mesh; warn in one line when the atlas fails its checks."""
        log.info("fitting an atlas of charts: %s", reason)
        one_chart = self.timings_  # what it took to find that one chart is not enough
        for name in [n for n in self.__dict__ if n.endswith("_") and not n.startswith("_")]:
            del self.__dict__[name]  # nothing of an earlier one-chart fit is left behind
        atlas = (self._new_atlas() if atlas is None else atlas).set_params(
            hidden_layers=hidden_layers, n_neighbors=n_neighbors).fit(points)
        self.atlas_ = atlas
        self.atlas_reason_ = reason
        self.mesh_ = atlas.mesh_
        self.timings_ = {**one_chart, **{f"atlas {k}": v for k, v in atlas.timings_.items()}}
        self.unexplained_ = unexplained_fraction(self.mesh_, points)
        self.neighbour_preservation_ = float(np.mean(
            [chart.neighbour_preservation_ for chart in atlas.charts_]))
        problems = list(atlas.faults_)
        if self.unexplained_ > UNEXPLAINED_LIMIT:
            problems.insert(0, f"the mesh leaves {100 * self.unexplained_:.0f} % of the "
                               "points farther than their noise allows")
        else:  # under the limit, in one patch: a region left out (of all the points given: the
            # embedding's outlier filter drops a part sampled much more sparsely than the rest)
            self.missed_region_ = missed_region(self.mesh_, self.__dict__.get("_given", points))
            if self.missed_region_[0] > MISSED_LIMIT:
                problems.insert(0, f"the mesh misses a region of the data, "
                                   f"{_in_words(self.missed_region_)} (a small piece apart "
                                   f"from the rest, or a part sampled more sparsely, left out)")
        if problems:
            warnings.warn(f"atlas of {len(atlas.charts_)} charts: {problems[0]}"
                          + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""),
                          ReconstructionWarning, stacklevel=3)
        return self

    def _new_mlp(self) -> AdaptiveMLP:
        if self.mlp is not None:
            return clone(self.mlp)
        return AdaptiveMLP(
            max_layers=self.max_layers,
            max_neurons=self.max_neurons,
            activation=self.activation,
            retrain=self.retrain,
            weight_decay=FINAL_WEIGHT_DECAY,
            random_state=self.random_state,
        )

    def _warm_tolerance(self, warm_start: SurfaceReconstructor) -> float:
        if self.warm_tolerance is not None:
            return float(self.warm_tolerance)
        distance, _ = cKDTree(warm_start.points_).query(warm_start.points_, k=2)
        return float(np.median(distance[:, 1]))

    def _check_faithful(self) -> None:
        """Measure how faithful the one-chart mesh is (``unexplained_`` is measured by `fit`);
        warn when it cannot be (closed, curled onto itself, layered): a wrong mesh is said,
        never returned silently."""
        self.neighbour_preservation_ = neighbour_preservation(self.points_, self.embedding_)
        volume = None if self._atlas_chart else volume_warning(self.points_)
        if volume:
            warnings.warn(volume, ReconstructionWarning, stacklevel=3)
        if self.unexplained_ > UNEXPLAINED_LIMIT:
            warnings.warn(
                f"the mesh leaves {100 * self.unexplained_:.0f} % of the points farther than "
                "their noise allows: the cloud is not one disc-like surface (closed, curled onto "
                "itself or in layers), which one chart of the paper's method cannot mesh, or it "
                "has more detail than the network holds",
                ReconstructionWarning, stacklevel=3,
            )
        elif self.missed_region_[0] > MISSED_LIMIT:  # the same words each time: said once
            log.info("missed region: %s", _in_words(self.missed_region_))
            warnings.warn(f"the mesh misses a region of the data: over {MISSED_LIMIT:.0%} of the "
                          "points, in one patch, lie farther than their noise allows (a "
                          "boundary that cut it off, or detail the network cannot hold; "
                          "missed_region_ says where)", ReconstructionWarning, stacklevel=3)
        # Said, not acted on: one layer of uniform or quantised noise (a depth camera's steps)
        # flattens the residuals as much as two layers do (a terrain with uniform noise: 1.83;
        # sent to the atlas, its Chamfer-L1 0.0013 -> 0.0043 and 3 times the time). Nor do a
        # point's nearest neighbours in 3D tell them apart: they lie on its side of the mesh in
        # both once the noise is wider than the spacing (correlation of a residual with its 6
        # neighbours' mean: a plane with uniform noise 0.81, two layers 0.87-0.97).
        kurtosis = self.residual_kurtosis_  # (found by `_fit_one_chart`)
        if kurtosis < LAYERED_KURTOSIS:
            warnings.warn(
                f"the points lie in two layers about the mesh, or their noise is not Gaussian "
                f"(residual kurtosis {kurtosis:.2f}, one Gaussian layer about 3): a closed "
                f"object with walls thinner than the noise is meshed through their middle as "
                f"one open sheet (an atlas, atlas='always' or --atlas always, joins them "
                f"closed, as thin shells, where solid parts face out)",
                ReconstructionWarning, stacklevel=3)

    def remesh(self, **params) -> trimesh.Trimesh:
        """Re-mesh with new ``lam``, ``depth``, ``n_corners``, ``boundary`` or ``grid_spacing``
        through the stored ONNX map (no retraining). Returns and stores ``mesh_``."""
        _check_known(params)
        if hasattr(self, "atlas_"):
            self._check_mesh_params_given(params)
            self.atlas_.up = self.up  # set_params(up=...) reaches the atlas's open join
            self.mesh_ = self.atlas_.remesh(**params)
            self.set_params(**{k: v for k, v in params.items() if v is not None})
            return self.mesh_
        self.remesh_unless(None, **params)
        return self.mesh_

    def remesh_unless(self, unchanged, **params) -> bool:
        """`remesh` with ``params`` unless ``unchanged(outline, spacing, grid)``, given the
        new outline (p, 2), grid spacing and `meshing.lattice_grid` (None off a lattice), says
        that what its caller uses of the mesh would come out as it is (an atlas's part of its
        chart: `reconstruct.chart_parts`). Then only the parameters, ``spline_`` and
        ``outline_`` are taken and ``mesh_`` is dropped. Returns whether it re-meshed."""
        _check_known(params)
        if not hasattr(self, "surface_map_"):
            raise NotFittedError("fit() the reconstructor (or load() a saved one) first")
        given = {k: v for k, v in params.items() if v is not None}
        previous = {k: getattr(self, k) for k in given}  # mesh parameters: plain attributes
        vars(self).update(given)  # (set_params's introspection: 0.3 ms of a chart's 8)
        try:
            self._check_mesh_params()
            return self._remeshed_unless(unchanged)
        except Exception:  # a rejected value, or one its boundary cannot take (a spline that
            vars(self).update(previous)  # collapses), leaves the model as it was
            raise

    def _remeshed_unless(self, unchanged) -> bool:
        started = time.perf_counter()
        interpolants, fit_input = self._boundary_points()
        spline = BoundarySpline(lam=self.lam, variance=self.variance).fit(fit_input)
        outline = self._extended(spline.polygon_, fit_input)
        spacing = self.grid_spacing or default_spacing(outline, len(self.embedding_))
        grid = None if self.grid_spacing is None else lattice_grid(outline, spacing)
        if unchanged is not None and unchanged(outline, spacing, grid):
            self.boundary_points_, self.spline_, self.outline_ = interpolants, spline, outline
            for name in ("mesh_", "vertices_2d_"):
                self.__dict__.pop(name, None)
            return False
        bounded = time.perf_counter()
        boundary_vertices = sample_ring(outline, spacing)
        vertices_2d, faces = mesh_inside(outline, boundary_vertices, spacing,
                                         lattice=grid is not None, grid=grid)
        vertices_3d = self.surface_map_(vertices_2d)
        self.boundary_points_ = interpolants
        self.spline_ = spline
        self.outline_ = outline
        self.vertices_2d_ = vertices_2d
        if grid is not None:
            self._outline_lattice = (outline, lattice_nodes(outline, spacing, grid))
        if self.up is not None and not self._faces_seen_side(vertices_3d, faces):
            faces = np.ascontiguousarray(faces[:, ::-1])
        self.mesh_ = trimesh.Trimesh(vertices_3d, faces, process=False)
        self.timings_ = {**getattr(self, "timings_", {}), "boundary": bounded - started,
                         "mesh": time.perf_counter() - bounded}
        log.info(
            "meshed: λ=%g, depth %d, %d interpolants, %d vertices, %d faces (%.0f ms)",
            self.lam,
            self.depth,
            len(interpolants),
            len(vertices_2d),
            len(faces),
            1000 * (time.perf_counter() - started),
        )
        return True

    def outline_lattice(self) -> tuple[np.ndarray, np.ndarray]:
        """`meshing.lattice_nodes` (first, used) of ``outline_`` on the lattice of
        ``grid_spacing`` (kept from the re-mesh that laid them)."""
        kept = self.__dict__.get("_outline_lattice")
        if kept is None or kept[0] is not self.outline_:
            kept = self._outline_lattice = (self.outline_,
                                            lattice_nodes(self.outline_, self.grid_spacing))
        return kept[1]

    def _faces_seen_side(self, vertices, faces) -> bool:
        """Whether the map's faces (f, 3) over ``vertices`` (v, 3) face the side the cloud was
        seen from (`join.faces_seen_side`): found on a fit's first mesh for each ``up`` and
        kept (the side follows the embedding, not λ or depth; 40 ms of a 50k-vertex re-mesh;
        `fit` drops it)."""
        key = tuple(float(x) for x in check_up(self.up))
        kept = self.__dict__.get("_seen_side")
        if kept is None or kept[0] != key:
            kept = self._seen_side = (key, faces_seen_side(vertices, faces, self.points_,
                                                           self.up))
        return kept[1]

    def _check_mesh_params_given(self, params) -> None:
        """Validate re-mesh parameters without keeping them (raises `InvalidInputError`)."""
        previous = self.get_params(deep=False)
        self.set_params(**{k: v for k, v in params.items() if v is not None})
        try:
            self._check_mesh_params()
        finally:
            self.set_params(**previous)

    def _extended(self, polygon: np.ndarray, given: SplineInput) -> np.ndarray:
        """The spline's ``polygon`` (p, 2) grown by `extend` spacings of the points along the
        boundary of the interpolants ``given``."""
        factor = self._extension()
        if factor == 0:
            return polygon
        return extend_outline(polygon, factor * self._border_spacing(given))

    def _extension(self) -> float:
        """The spacings by which the outline is grown (`extend`) at the present depth."""
        depth = self.depth if self.boundary == "multidepth" else 1
        return {
            "auto": border_inset(depth) - border_inset(1),
            "border": border_inset(depth),
        }.get(self.extend, self.extend)

    def _border_spacing(self, given: SplineInput) -> float:
        """`outline.border_spacing` of the points along the loop of the interpolants ``given``,
        kept for them: a property of the points, not of λ, so measured on the loop once
        rather than on each λ's spline (1 ms of a chart's 4 ms re-mesh; the spline's differ
        from it by 0–2 % at the median over the figurine's and dragon's charts at depth 2–3,
        λ 0.5–3, within ±7 % for 90 % of them)."""
        cache = self.__dict__.setdefault("_boundary_cache", {})
        kept = cache.setdefault("border spacing", {})
        key = (self.boundary, self.depth, self.n_corners)
        if key not in kept or kept[key][0] is not given:
            if "tree" not in cache:
                cache["tree"] = PointTree(self.embedding_)
            loop = np.vstack([given.loop, given.loop[:1]])
            kept[key] = given, border_spacing(loop, cache["tree"])
        return kept[key][1]

    def sample_boundaries(self, depths) -> None:
        """Sample the boundary at each of ``depths`` into the cache (`_boundary_points`), with
        what a re-mesh takes from the samples whatever λ (their `spline_input`, the points'
        spacing along them), so a re-mesh to one of them need not (1.4 ms a chart the first
        time). A depth with too few interpolants for the spline (a small chart at a depth it
        was not fitted with) is skipped: a re-mesh there says so itself. ``depth`` is left as
        it was."""
        fitted_depth = self.depth
        try:
            for depth in depths:
                self.depth = depth
                try:
                    given = self._boundary_points()[1]
                    if self._extension() != 0:
                        self._border_spacing(given)
                except (InvalidInputError, FitError) as exc:
                    log.info("no boundary at depth %d (%s)", depth, one_line(exc))
                    self._boundary_cache.pop((self.boundary, depth, self.n_corners), None)
        finally:
            self.depth = fitted_depth

    def prepare_remeshing(self) -> None:
        """Take now what a loaded model's first re-mesh would take once: `sample_boundaries`
        of the depths it holds samples of, and its network's first run (a re-meshing worker's
        copies of a hook's 94 charts: their first re-mesh 454 ms, the next 292; 319 and 286
        prepared)."""
        depths = sorted({key[1] for key in self.__dict__.get("_boundary_cache", {})
                         if isinstance(key, tuple) and key[0] == self.boundary})
        self.sample_boundaries(depths)
        self.surface_map_(np.asarray(self.embedding_[:1], float))

    def _boundary_points(self) -> tuple[np.ndarray, SplineInput]:
        """The boundary interpolants (k, 2) of the present boundary parameters, and their
        `spline_input` (both kept for the next re-mesh)."""
        cache = self.__dict__.setdefault("_boundary_cache", {})
        key = (self.boundary, self.depth, self.n_corners)
        if key not in cache:
            if self.boundary == "pca":
                sampler = PCABoundary()
                cache[key] = sampler.fit(self.embedding_).points_
            else:
                sampler = MultiDepthBoundary(depth=self.depth, n_corners=self.n_corners)
                if "geometry" not in cache:  # the same at every depth
                    cache["geometry"] = boundary_geometry(self.embedding_, sampler.n_neighbors,
                                                          sampler.density_factor)
                cache[key] = sampler.fit(self.embedding_, cache["geometry"]).points_
        inputs = cache.setdefault("spline", {})  # of the interpolants kept, not of replaced ones
        if key not in inputs or inputs[key][0] is not cache[key]:
            inputs[key] = cache[key], spline_input(cache[key])
        return inputs[key]

    def _check_mesh_params(self) -> None:
        if not (np.isfinite(self.lam) and self.lam >= 0):
            raise InvalidInputError(f"lam must be a finite number >= 0, got {self.lam}")
        if int(self.depth) != self.depth or self.depth < 1:
            raise InvalidInputError(f"depth must be a whole number >= 1, got {self.depth}")
        if self.n_corners < 8:
            raise InvalidInputError(
                f"n_corners must be >= 8 (the paper's method), got {self.n_corners}"
            )
        if self.boundary not in ("multidepth", "pca"):
            raise InvalidInputError(
                f"boundary must be 'multidepth' or 'pca', got {self.boundary!r}"
            )
        if self.variance not in ("local", "global"):
            raise InvalidInputError(
                f"variance must be 'local' or 'global', got {self.variance!r}"
            )
        if not (self.extend in ("auto", "border") or (
            not isinstance(self.extend, str) and np.isfinite(self.extend) and self.extend >= 0
        )):
            raise InvalidInputError(
                f"extend must be 'auto', 'border' or a number >= 0, got {self.extend!r}"
            )
        if self.grid_spacing is not None and not self.grid_spacing > 0:
            raise InvalidInputError(f"grid_spacing must be > 0, got {self.grid_spacing}")
        if self.up is not None:
            check_up(self.up)

    # -- persistence ---------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write the fitted state (embedded points, ONNX model, parameters) atomically; of an
        atlas, every chart's state and what re-joining needs (`AtlasReconstructor.state`)."""
        if hasattr(self, "atlas_"):
            meta, arrays = self.atlas_.state()
            meta["reconstructor"] = {"params": self._saved_params(),
                                     "atlas_reason": self.atlas_reason_}
            return write_state(path, meta, arrays)
        if not hasattr(self, "surface_map_"):
            raise NotFittedError("nothing to save: fit() the reconstructor first")
        return write_state(path, *self.state())

    def _saved_params(self) -> dict:
        return {k: v for k, v in self.get_params(deep=False).items() if k not in _TRAINING_PARAMS}

    def state(self, prefix: str = "") -> tuple[dict, dict[str, np.ndarray]]:
        """The one-chart fitted state: (meta, arrays named ``prefix`` + embedding / points /
        onnx / boundary samples), as `save` writes it (`pipeline_state.reconstruction_state`)."""
        return reconstruction_state(self, self._saved_params(), prefix)

    @classmethod
    def from_state(cls, meta: dict, arrays: dict, prefix: str = "") -> SurfaceReconstructor:
        """Rebuild a one-chart reconstruction from `state`; it can `remesh()` at once
        (`pipeline_state.reconstruction_from_state`)."""
        return reconstruction_from_state(cls, meta, arrays, prefix)

    @classmethod
    def load(cls, path: str | os.PathLike) -> SurfaceReconstructor:
        """Read a state written by `save` (one chart or an atlas) or `AtlasReconstructor.save`;
        the result can `remesh()` at once. A damaged or foreign file raises
        `InvalidInputError` in one line."""
        from .atlas import ATLAS_FORMAT, AtlasReconstructor

        meta, arrays = read_state(path)
        kind = meta.get("format")
        if kind not in (STATE_FORMAT, ATLAS_FORMAT):
            raise InvalidInputError(f"{path}: unsupported state format {kind!r}")
        try:
            if kind == STATE_FORMAT:
                return cls.from_state(meta, arrays)
            atlas = AtlasReconstructor.from_state(meta, arrays)
            outer = meta.get("reconstructor")
            if outer is None:  # `AtlasReconstructor.save`'s: its parameters the ones both have
                shared = (cls().get_params(deep=False).keys() & atlas.get_params(deep=False)
                          ) - set(_TRAINING_PARAMS)  # as `save` keeps them: not the atlas's
                outer = {"params": {k: getattr(atlas, k) for k in shared},
                         "atlas_reason": "saved as an atlas (AtlasReconstructor.save)"}
            self = cls(**outer["params"])
            self.atlas_, self.atlas_reason_ = atlas, str(outer["atlas_reason"])
            return self
        except Exception as exc:  # a missing array, a bad header field, a broken ONNX model
            raise InvalidInputError(
                f"{path}: damaged reconstruction state ({one_line(exc)})") from exc


def _in_words(missed: tuple) -> str:
    """`faithfulness.missed_region`'s (share, centre) in words."""
    share, centre = missed
    return f"{share:.1%} of the points, round ({', '.join(f'{c:.3g}' for c in centre)})"


def _in_pieces(exc: CloudInPiecesError) -> str:
    """Why a cloud in pieces goes to the atlas, in words."""
    sizes = exc.sizes
    return (f"its neighbourhood graph is in {len(sizes)} pieces, the largest {sizes[0]} of "
            f"{sizes.sum()} points (several objects or parts apart)")
