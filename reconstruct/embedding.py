"""Outlier removal and the 3D → 2D embedding of a surface cloud (the paper's first step).

Methods: full Isomap (Tenenbaum et al. 2000: Dijkstra between all points, classical MDS),
modified LLE (Zhang & Wang 2006, scikit-learn), and landmark Isomap (de Silva & Tenenbaum 2004:
landmarks by geodesic max-min sampling, Dijkstra from the landmarks only, classical MDS of the
landmarks, distance-based triangulation of every other point; memory O(n * landmarks)).
K is chosen by `reconstruct.neighbors.choose_n_neighbors` unless given (for modified LLE at
least MLLE_MIN_K). Gross outliers are dropped first, and only the largest piece of the kNN graph
is embedded (`support_` marks the embedded input points).
"""

from __future__ import annotations

import logging
import warnings

import numpy as np
from scipy.sparse.csgraph import dijkstra
from scipy.spatial.distance import cdist
from sklearn.base import BaseEstimator
from sklearn.manifold import LocallyLinearEmbedding

from .errors import (
    CloudInPiecesError,
    DegenerateCloudError,
    FitError,
    InvalidInputError,
    ReconstructionWarning,
)
from .neighbors import (
    K_MAX,
    choose_n_neighbors,
    classical_mds,
    component_sizes,
    knn_graph,
    nearest_neighbors,
    residual_variance,
)
from .outliers import statistical_outlier_mask
from .threads import single_threaded
from .validation import check_spread

log = logging.getLogger(__name__)

METHODS = ("auto", "isomap", "mlle", "landmark")
#: "auto" picks modified LLE below this many points (the paper: MLLE wins at 36 and 100 points,
#: Isomap at 144 and more), full Isomap up to LANDMARK_ABOVE, landmark Isomap above.
MLLE_BELOW = 120
LANDMARK_ABOVE = 3000
MIN_POINTS = 8
#: Full Isomap holds an n x n float64 matrix (twice): refuse beyond this (0.8 GB each).
ISOMAP_MAX_POINTS = 10_000
#: Modified LLE is unstable below 6 neighbours (measured on the paper's cones and torus).
MLLE_MIN_K = 6
#: Only gross outliers: mean neighbour distance above 2.5x the median (see outliers.py).
OUTLIER_MIN_RATIO = 2.5
#: At most this many (landmark, point) pairs enter a residual variance.
_MAX_PAIRS = 2_000_000


def default_n_landmarks(n_points: int) -> int:
    """Landmarks for landmark Isomap: 2 sqrt(n), clipped to [100, 250]."""
    return int(np.clip(2 * np.sqrt(n_points), 100, 250))


class SurfaceEmbedding(BaseEstimator):
    """Embed a surface cloud (n, 3) into the plane (m, 2), m <= n.

    Parameters
    ----------
    method : "auto", "isomap", "mlle" or "landmark" (see module docstring).
    n_neighbors : K of the kNN graph; None chooses it (minimum landmark residual variance).
    n_landmarks : landmarks of landmark Isomap; None uses `default_n_landmarks`.
    remove_outliers : drop statistical outliers first (`statistical_outlier_mask`).
    other_pieces : the share of the points that the graph's pieces other than the largest may
        hold: the largest is embedded (with a warning when there are others);
        `CloudInPiecesError` beyond it. Pieces under ``min_piece`` points (stray points) do not
        count.
    random_state : seed of the landmark sampling and the eigensolvers.

    Fitted attributes: ``embedding_`` (m, 2) float64 in the cloud's length unit (geodesic
    distances; modified LLE is scaled to them by least squares), ``support_`` (n,) bool (inlier
    and in the largest piece of the graph), ``inliers_`` (n,) bool (not an outlier, in any
    piece: the points the embedded surface must account for), ``method_``, ``n_neighbors_``,
    ``residual_variance_``
    (1 - R^2 of geodesic vs embedded distances), ``landmarks_`` (indices into the embedded
    points: the landmarks of landmark Isomap; otherwise the points whose geodesic distances
    scored ``residual_variance_``).
    """

    def __init__(
        self,
        method: str = "auto",
        n_neighbors: int | None = None,
        n_landmarks: int | None = None,
        remove_outliers: bool = True,
        other_pieces: float = 0.5,
        min_piece: int = 1,
        random_state: int | None = 0,
    ):
        self.method = method
        self.n_neighbors = n_neighbors
        self.n_landmarks = n_landmarks
        self.remove_outliers = remove_outliers
        self.other_pieces = other_pieces
        self.min_piece = min_piece
        self.random_state = random_state

    def fit(self, points, y=None) -> SurfaceEmbedding:
        """points : (n, 3) float, finite. Returns self."""
        points = self._check_input(points)
        support = np.ones(len(points), dtype=bool)
        if self.remove_outliers:
            support = statistical_outlier_mask(points, min_ratio=OUTLIER_MIN_RATIO)
        kept = np.flatnonzero(support)
        method = self._resolve_method(len(kept))
        self._check_count(len(kept), method, "after outlier removal")

        if self.n_neighbors is None:
            distances, indices = nearest_neighbors(points[kept], 2 * K_MAX)
            choice = choose_n_neighbors(
                points[kept], distances, indices, random_state=self.random_state
            )
            k = choice.n_neighbors
            if method == "mlle":
                k = min(max(k, MLLE_MIN_K), len(kept) - 1)
        else:
            k = min(int(self.n_neighbors), len(kept) - 1)
            distances, indices = nearest_neighbors(points[kept], k)
        graph = knn_graph(distances, indices, k)
        self.inliers_ = support.copy()
        in_piece = self._largest_piece(graph)
        if not in_piece.all():
            kept, graph = kept[in_piece], graph[in_piece][:, in_piece].tocsr()
        support[:] = False
        support[kept] = True
        self._check_count(len(kept), method, "in the largest piece of the graph")

        n_landmarks = self.n_landmarks or default_n_landmarks(len(kept))
        log.info(
            "embedding %d points: %s, K=%d%s",
            len(kept),
            {"isomap": "Isomap", "mlle": "modified LLE", "landmark": "landmark Isomap"}[method],
            k,
            f", {min(n_landmarks, len(kept))} landmarks" if method == "landmark" else "",
        )
        rng = np.random.default_rng(self.random_state)
        if method == "landmark":
            embedding, landmarks, geodesic = landmark_isomap(graph, n_landmarks, rng)
        elif method == "isomap":
            geodesic = dijkstra(graph, directed=True)
            landmarks = np.arange(len(kept))
            embedding = classical_mds(geodesic**2)[0]
        else:
            embedding = _modified_lle(points[kept], k, rng)
            landmarks = _pair_sample(len(kept), len(kept), rng)
            geodesic = dijkstra(graph, directed=True, indices=landmarks)
        columns = _pair_sample(len(kept), len(landmarks), rng)
        geodesic = geodesic[:, columns]
        embedded = cdist(embedding[landmarks], embedding[columns])
        if method == "mlle":
            if not np.sum(embedded**2) > 0:
                raise FitError(f"modified LLE with K={k} collapsed the cloud to a point")
            embedding = embedding * (np.sum(geodesic * embedded) / np.sum(embedded**2))
            embedded = cdist(embedding[landmarks], embedding[columns])

        self.embedding_ = np.ascontiguousarray(embedding, dtype=np.float64)
        self.support_ = support
        self.method_ = method
        self.n_neighbors_ = int(k)
        self.landmarks_ = landmarks
        self.residual_variance_ = residual_variance(geodesic, embedded)
        return self

    def fit_transform(self, points, y=None) -> np.ndarray:
        """Fit and return ``embedding_`` (m, 2)."""
        return self.fit(points).embedding_

    # -- checks -------------------------------------------------------------------------------

    def _check_input(self, points) -> np.ndarray:
        if self.method not in METHODS:
            raise InvalidInputError(
                f"unknown embedding method {self.method!r}; use one of {METHODS}"
            )
        if self.n_neighbors is not None and int(self.n_neighbors) < 2:
            raise InvalidInputError(f"n_neighbors must be >= 2, got {self.n_neighbors}")
        if self.method == "mlle" and self.n_neighbors is not None and int(self.n_neighbors) < 3:
            raise InvalidInputError(f"modified LLE needs n_neighbors >= 3, got {self.n_neighbors}")
        if self.n_landmarks is not None and int(self.n_landmarks) < 3:
            raise InvalidInputError(f"n_landmarks must be >= 3, got {self.n_landmarks}")
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise InvalidInputError(f"expected points of shape (n, 3), got {points.shape}")
        self._check_count(len(points), self._resolve_method(len(points)), "given")
        check_spread(points)
        return points

    def _resolve_method(self, n_points: int) -> str:
        if self.method != "auto":
            return self.method
        if n_points < MLLE_BELOW:
            return "mlle"
        return "isomap" if n_points <= LANDMARK_ABOVE else "landmark"

    def _check_count(self, n_points: int, method: str, where: str) -> None:
        needed = MIN_POINTS
        if self.n_neighbors is not None:
            needed = max(needed, int(self.n_neighbors) + 1)
        if method == "landmark" and self.n_landmarks is not None:
            needed = max(needed, int(self.n_landmarks))
        if n_points < needed:
            raise InvalidInputError(
                f"{n_points} points {where}; {method} embedding needs at least {needed}"
            )
        if method == "isomap" and n_points > ISOMAP_MAX_POINTS:
            raise InvalidInputError(
                f"full Isomap of {n_points} points needs {n_points} x {n_points} matrices; "
                f"use method='landmark' above {ISOMAP_MAX_POINTS}"
            )

    def _largest_piece(self, graph) -> np.ndarray:
        labels, sizes = component_sizes(graph)
        largest, total = int(sizes.max()), int(sizes.sum())
        if len(sizes) > 1:
            rest = np.delete(sizes, np.argmax(sizes))
            if rest[rest >= self.min_piece].sum() > self.other_pieces * total:
                raise CloudInPiecesError(
                    f"neighbourhood graph has {len(sizes)} pieces; the largest holds "
                    f"{largest} of {total} points", np.sort(sizes)[::-1]
                )
            warnings.warn(
                f"neighbourhood graph has {len(sizes)} pieces; reconstructing the largest "
                f"({largest} of {total} points)",
                ReconstructionWarning,
                stacklevel=3,
            )
        return labels == np.argmax(sizes)


def landmark_isomap(graph, n_landmarks: int, rng: np.random.Generator):
    """Landmark Isomap of a connected symmetric graph (n nodes, CSR).

    Landmarks by geodesic max-min sampling (each new landmark is the node farthest from the
    chosen ones; its Dijkstra run is the one we need anyway), classical MDS of the landmarks,
    distance-based triangulation of all nodes. Returns embedding (n, 2), landmarks (l,) and the
    geodesic distances (l, n) from the landmarks.
    """
    n = graph.shape[0]
    n_landmarks = min(int(n_landmarks), n)
    landmarks = np.empty(n_landmarks, dtype=np.intp)
    geodesic = np.empty((n_landmarks, n))
    nearest = np.full(n, np.inf)
    landmarks[0] = rng.integers(n)
    for i in range(n_landmarks):
        geodesic[i] = dijkstra(graph, directed=True, indices=landmarks[i])
        np.minimum(nearest, geodesic[i], out=nearest)
        if i + 1 < n_landmarks:
            landmarks[i + 1] = np.argmax(nearest)
    squared_landmarks = geodesic[:, landmarks] ** 2
    with single_threaded():  # the same bits whatever the shell sets (BLAS threads reorder sums)
        _, values, vectors = classical_mds(squared_landmarks)
        if values[1] <= 1e-12 * values[0]:
            raise DegenerateCloudError("the landmarks span no 2D surface (geodesically collinear)")
        # y_x = -1/2 L# (delta_x - delta_mean), L# rows = v_k / sqrt(lambda_k).
        pseudo_inverse = vectors / np.sqrt(values)
        mean_squared = squared_landmarks.mean(axis=1)
        embedding = -0.5 * ((geodesic**2 - mean_squared[:, None]).T @ pseudo_inverse)
    return embedding, landmarks, geodesic


def _modified_lle(points, k: int, rng: np.random.Generator) -> np.ndarray:
    """Modified LLE (scikit-learn) of (m, 3) points with K neighbours; (m, 2)."""
    k = max(3, min(int(k), len(points) - 1))
    solver = "dense" if len(points) <= 1000 else "arpack"
    model = LocallyLinearEmbedding(
        n_neighbors=k,
        n_components=2,
        method="modified",
        eigen_solver=solver,
        random_state=int(rng.integers(2**31 - 1)),
    )
    try:
        return model.fit_transform(points)
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise FitError(f"modified LLE failed with K={k}: {exc}") from exc


def _pair_sample(n: int, n_rows: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted columns (<= n) so that n_rows x columns stays under _MAX_PAIRS."""
    n_columns = min(n, max(1, _MAX_PAIRS // max(n_rows, 1)))
    if n_columns == n:
        return np.arange(n)
    return np.sort(rng.choice(n, size=n_columns, replace=False))
