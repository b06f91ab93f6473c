"""Split any surface cloud (open or closed, any genus, sheets close together) into overlapping
disc-like charts, each small enough for one searched network of the paper's method.

On the sheet-respecting graph (`reconstruct.sheet_graph`) every connected piece gets
``ceil(size / chart_size)`` seeds by geodesic farthest-point sampling; each point joins its
geodesically nearest seed (a geodesic Voronoi partition: the charts' *cores*, which tile the
cloud without overlap). Each chart is its core widened by a ring of the points within
``overlap`` median spacings (geodesic) of it, so neighbouring charts share points and their
fitted surfaces can be oriented alike and joined. A chart found unfaithful later (folded
embedding, unexplained points) is `split` in two along the same graph.

Points the graph leaves in pieces smaller than ``min_points`` (stray points, points midway
between two sheets that the graph joins to neither) belong to no chart: ``labels_`` is −1.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import (
    breadth_first_order,
    connected_components,
    dijkstra,
    minimum_spanning_tree,
)
from sklearn.base import BaseEstimator

from .errors import DegenerateCloudError
from .sheet_graph import SheetGraph
from .validation import check_points

log = logging.getLogger(__name__)

#: A core is within its normal cone when this share of its points (at most) lie outside: single
#: normals of a noisy cloud stray (PCA of a neighbourhood at σ ≈ spacing).
CONE_QUANTILE = 0.03


def geodesic_seeds(graph, members: np.ndarray, n_seeds: int, random_state=None) -> np.ndarray:
    """Geodesic farthest-point seeds among ``members`` (indices into the (n, n) ``graph``,
    one connected piece). Returns (min(n_seeds, len(members)),) indices into the graph."""
    rng = np.random.default_rng(random_state)
    sub = graph[members][:, members]
    start = int(rng.integers(len(members)))
    # begin at the point farthest from a random one (an extremity), then max-min
    distance = dijkstra(sub, directed=False, indices=start)
    chosen = [int(np.argmax(np.where(np.isfinite(distance), distance, -1)))]
    nearest = dijkstra(sub, directed=False, indices=chosen[0])
    for _ in range(1, min(int(n_seeds), len(members))):
        chosen.append(int(np.argmax(np.where(np.isfinite(nearest), nearest, -1))))
        np.minimum(nearest, dijkstra(sub, directed=False, indices=chosen[-1]), out=nearest)
    return members[np.array(chosen)]


def oriented_normals(graph, members: np.ndarray, normals: np.ndarray, root: int) -> np.ndarray:
    """Unoriented ``normals`` (n, 3) of ``members`` oriented alike by walking the graph from
    ``root`` (an index into the graph): (len(members), 3); unreached points keep their sign.
    The walk follows a minimum spanning tree of 1 − |n_i · n_j| (Hoppe et al. 1992), so a
    stray normal is reached last and flips nothing beyond itself."""
    sub = graph[members][:, members].tocoo()
    local = normals[members]
    weight = 1.0 + 1e-6 - np.abs(np.einsum("ei,ei->e", local[sub.row], local[sub.col]))
    sub = minimum_spanning_tree(coo_matrix((weight, (sub.row, sub.col)), shape=sub.shape))
    local_root = int(np.flatnonzero(members == root)[0])
    order, parent = breadth_first_order(sub, local_root, directed=False)
    oriented = normals[members].copy()
    for node in order[1:]:  # parents come first in breadth-first order
        if oriented[node] @ oriented[parent[node]] < 0:
            oriented[node] = -oriented[node]
    return oriented


def voronoi_cells(graph, members: np.ndarray, seeds: np.ndarray) -> list[np.ndarray]:
    """Split ``members`` (indices into ``graph``) among ``seeds`` by geodesic distance.
    Returns one index array per seed (empty ones dropped)."""
    sub = graph[members][:, members]
    local = np.searchsorted(members, seeds) if np.all(np.diff(members) > 0) else np.array(
        [np.flatnonzero(members == s)[0] for s in seeds])
    _, _, sources = dijkstra(sub, directed=False, indices=local, min_only=True,
                             return_predecessors=True)
    cells = [members[sources == s] for s in local]
    return [cell for cell in cells if len(cell)]


def _most_central(graph, core: np.ndarray) -> int:
    """The point of ``core`` farthest (geodesically) from the core's border: the centre of a
    disc-like core. Two sweeps from an extremity approximate it cheaply."""
    sub = graph[core][:, core]
    far = dijkstra(sub, directed=False, indices=0)
    a = int(np.argmax(np.where(np.isfinite(far), far, -1)))
    from_a = dijkstra(sub, directed=False, indices=a)
    b = int(np.argmax(np.where(np.isfinite(from_a), from_a, -1)))
    from_b = dijkstra(sub, directed=False, indices=b)
    both = np.where(np.isfinite(from_a + from_b), np.abs(from_a - from_b) + 0.0, np.inf)
    # the midpoint of the longest path: about equally far from both extremities
    return int(core[np.argmin(both + 1e-9 * from_a)])


#: Pieces of the graph smaller than this belong to no chart (stray points).
MIN_CHART_POINTS = 50


class ChartDecomposition(BaseEstimator):
    """Overlapping disc-like charts of a surface cloud (n, 3).

    Parameters
    ----------
    chart_size : target number of points in a chart's core (what one searched net holds).
    overlap : width of the ring added to each core, in median point spacings (geodesic).
    min_points : pieces of the graph smaller than this belong to no chart.
    max_angle : a core is split until its normals lie within this angle (degrees) of the
        normal at its most central point.
    graph : an unfitted `SheetGraph` (its parameters); None uses the defaults.
    random_state : seed of the farthest-point sampling.

    Fitted attributes: ``graph_`` (fitted `SheetGraph`), ``cores_`` list of (c_i,) index
    arrays tiling the charted points, ``labels_`` (n,) core of each point (−1: none),
    ``spacing_`` median point spacing, ``n_charts_``.
    """

    def __init__(self, chart_size: int = 2500, overlap: float = 4.0,
                 min_points: int = MIN_CHART_POINTS,
                 max_angle: float = 70.0, graph: SheetGraph | None = None,
                 random_state: int | None = 0):
        self.chart_size = chart_size
        self.overlap = overlap
        self.min_points = min_points
        self.max_angle = max_angle
        self.graph = graph
        self.random_state = random_state

    def fit(self, points, y=None, graph: SheetGraph | None = None) -> ChartDecomposition:
        """points : (n, 3). ``graph``: an already fitted `SheetGraph` of the same points."""
        points = check_points(points)
        if graph is None:
            graph = (self.graph if self.graph is not None else SheetGraph()).fit(points)
        self.graph_ = graph
        self.spacing_ = float(np.median(graph.spacing_))
        adjacency = graph.graph_
        n_pieces, piece = connected_components(adjacency, directed=False)
        sizes = np.bincount(piece, minlength=n_pieces)
        cores = []
        for label in np.flatnonzero(sizes >= self.min_points):
            members = np.flatnonzero(piece == label)
            n_seeds = int(np.ceil(len(members) / self.chart_size))
            seeds = geodesic_seeds(adjacency, members, n_seeds, self.random_state)
            cores += voronoi_cells(adjacency, members, seeds)
        # slivers joined to the core they share most edges with wrap cores round thin parts (a
        # chair's 7 mm legs: embeddings folded, meshes through the legs' middles): such cores
        # are split again, and the slivers that leaves join a neighbour only within the cone
        # (bench.atlas 20k, seeds 0-2: chair denoise 0.565 / 0.532 / 0.529 with the first
        # merge alone, 0.456 / 0.501 / 0.480 with the slivers of the second split left alone
        # (hook seed 0: 127 cores, 53 slivers), 0.499 / 0.475 / 0.433 now (95 cores, 16))
        cores = self._merged_small(self._within_cone(cores), len(points))
        cores = self._merged_small(self._within_cone(cores), len(points), cone=True)
        if not cores:
            raise DegenerateCloudError(
                f"no piece of the neighbourhood graph has {self.min_points} points: "
                "the cloud is too sparse or too noisy to chart")
        self.cores_ = cores
        self._relabel(len(points))
        left = int(np.sum(self.labels_ < 0))
        log.info("%d charts of %d points (%d points in no chart, %d graph pieces)",
                 len(cores), len(points), left, n_pieces)
        return self

    def _within_cone(self, cores: list[np.ndarray]) -> list[np.ndarray]:
        """Split cores until each one's normals (oriented along the graph from its most
        central point) lie within ``max_angle`` of that point's normal: a tube's section or a
        cap wider than a hemisphere is not a disc."""
        adjacency = self.graph_.graph_
        limit = np.cos(np.radians(self.max_angle))
        done, todo = [], list(cores)
        while todo:
            core = todo.pop()
            if len(core) < 2 * self.min_points:
                done.append(core)
                continue
            centre, agreement = self._cone_agreement(core)
            if np.quantile(agreement, CONE_QUANTILE) >= limit:
                done.append(core)
                continue
            seeds = np.array([centre, core[np.argmin(agreement)]])
            cells = voronoi_cells(adjacency, core, seeds)
            if len(cells) < 2:
                done.append(core)
                continue
            todo += cells
        return done

    def _cone_agreement(self, core: np.ndarray) -> tuple[int, np.ndarray]:
        """(the most central point of ``core``, (c,) cosines between its normal and the
        core's normals oriented along the graph from it)."""
        adjacency, normals = self.graph_.graph_, self.graph_.normals_
        centre = _most_central(adjacency, core)
        oriented = oriented_normals(adjacency, core, normals, centre)
        return centre, oriented @ normals[centre] * np.sign(
            oriented[np.flatnonzero(core == centre)[0]] @ normals[centre])

    def _merged_small(self, cores: list[np.ndarray], n: int,
                      cone: bool = False) -> list[np.ndarray]:
        """Cores under 1/25 of ``chart_size`` (slivers the cone split leaves at edges and
        corners; a network fitted to a few dozen points folds) join the neighbouring core they
        share most graph edges with; with ``cone``, the one of most edges among those that stay
        within the cone with them, and a sliver no neighbour can take stays a core."""
        smallest = max(self.min_points, self.chart_size // 25)
        limit = np.cos(np.radians(self.max_angle))
        labels = np.full(n, -1)
        for index, core in enumerate(cores):
            labels[core] = index
        edges = self.graph_.graph_.tocoo()
        for index in np.argsort([len(c) for c in cores]):
            core = np.flatnonzero(labels == index)
            if len(core) == 0 or len(core) >= smallest:
                continue
            touching = labels[edges.col[np.isin(edges.row, core)]]
            touching = touching[(touching >= 0) & (touching != index)]
            shared = np.bincount(touching) if len(touching) else np.zeros(0, int)
            for neighbour in np.argsort(-shared, kind="stable")[:np.count_nonzero(shared)]:
                joined = np.union1d(core, np.flatnonzero(labels == neighbour))
                if not cone or np.quantile(self._cone_agreement(joined)[1],
                                           CONE_QUANTILE) >= limit:
                    labels[core] = neighbour
                    break
        merged = [np.flatnonzero(labels == index) for index in range(len(cores))]
        return [core for core in merged if len(core)]

    @property
    def n_charts_(self) -> int:
        return len(self.cores_)

    def _relabel(self, n: int) -> None:
        self.labels_ = np.full(n, -1)
        for index, core in enumerate(self.cores_):
            self.labels_[core] = index

    def chart(self, index: int) -> np.ndarray:
        """Indices (m,) of chart ``index``: its core and the ring within ``overlap`` spacings."""
        return self.members(self.cores_[index])

    def members(self, core: np.ndarray) -> np.ndarray:
        """Indices (m,) of the chart of ``core`` (point indices): it and the ring within
        ``overlap`` spacings."""
        reach = self.overlap * self.spacing_
        distance = dijkstra(self.graph_.graph_, directed=False, indices=core, min_only=True,
                            limit=reach)
        return np.flatnonzero(np.isfinite(distance))

    def split(self, index: int, parts: int = 2, cells=None) -> list[int]:
        """Split chart ``index``'s core in ``parts`` along the graph (or in ``cells``, as
        `split_cells` gave them); returns the indices of the new charts (the first replaces
        ``index``). A core that cannot be split keeps one."""
        cells = self.split_cells(index, parts) if cells is None else cells
        self.cores_[index] = cells[0]
        new = [index]
        for cell in cells[1:]:
            self.cores_.append(cell)
            new.append(len(self.cores_) - 1)
        self._relabel(len(self.labels_))
        return new

    def split_cells(self, index: int, parts: int = 2) -> list[np.ndarray]:
        """The cores (arrays of point indices) `split` cuts chart ``index``'s in, without
        cutting it: the pieces the graph leaves of it, else ``parts`` geodesic Voronoi cells."""
        core = self.cores_[index]
        sub = self.graph_.graph_[core][:, core]
        n_pieces, piece = connected_components(sub, directed=False)
        if n_pieces > 1:  # a core cut in pieces by the graph: the pieces are the split
            return [core[piece == p] for p in range(n_pieces)]
        seeds = geodesic_seeds(self.graph_.graph_, core, parts, self.random_state)
        return voronoi_cells(self.graph_.graph_, core, seeds)
