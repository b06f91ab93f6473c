"""Boundary interpolants of a 2D embedding: the paper's multi-depth path sampling and the
Yumer–Kara baseline (PCA corners, outermost polyline). (About 400 lines: the two samplers share
the wedge geometry and path search below, which would be split across files by one caller.)

Both trace corner-to-corner shortest paths (Dijkstra) over k-nearest-neighbour graphs of the
points in the angular wedge between two adjacent corners, seen from the centroid. The paper
segments "point space into rectangles containing all points between one corner and its
adjacent corner"; an axis-aligned rectangle misses the part of the outline that bulges past
both corners whenever the outline turns through an axis direction between them, so we use the
wedge: every point whose direction from the centroid lies between the two corners'. That is the
rectangle's intent for any orientation, and the sector geometry the corners come from.

Path weights: an edge i → j costs ``c1 * d_s + c2 * d_c`` with ``d_s = |p_i - p_j|`` and
``d_c`` ≥ 0 the depth of the next point below the outer envelope of the remaining points: the
polygon joining, in angular order about the centroid c, the outermost point of each fine
sector (about √m sectors), and d_c the point's perpendicular distance below the edge of that
polygon above it. The paper's plain distance to the centroid would reward cutting through the
interior; measured down from the envelope it penalises closeness to the centroid instead, is 0
on the outside, keeps weights ≥ 0 for Dijkstra and is in the units of ``d_s``, so ``c1, c2`` do
not depend on the embedding's scale. Measured across the envelope's edges rather than along the
rays (each sector's largest radius minus the point's), a point on a side that the rays meet at
a grazing angle, as on the long sides of an elongated region, is not taken for an inner one.

Robustness and speed: outliers (sparse neighbourhoods) are never corners or path points; only
an outer band of points enters the graphs, and each wedge is tried first on a thin outer band
(2 spacings), where a sparse outer point's nearest neighbours are other outer points rather
than the denser interior. A wedge whose corners are not connected falls back to all its points,
to 4k neighbours, then to a straight segment (empty sectors simply have no corner). The graphs
also hold the Delaunay edges up to 3 spacings long: where the outline meets the rays from the
centroid at a grazing angle (the arch that Isomap makes of a half torus), an outer point's k
nearest neighbours can all lie inwards, and a kNN graph alone then cuts the corner. The depths
are merged into one loop by each point's arc-length position projected onto the outermost loop;
a deeper point more than 2 spacings per depth inside it is dropped (its path cut across).
This is a star-shaped view from the centroid: a C-shaped region is closed across its mouth.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import Delaunay, QhullError, cKDTree
from sklearn.base import BaseEstimator

from .errors import DegenerateCloudError, InvalidInputError
from .mesh_edges import half_edges

log = logging.getLogger(__name__)

#: Thickness, in point spacings, of the outer band whose kNN graph is tried first at each depth.
_OUTER = 2.0
#: Longest Delaunay edge, in point spacings, added to the paths' kNN graphs.
_REACH = 3.0


class MultiDepthBoundary(BaseEstimator):
    """The paper's multi-depth path sampling of a 2D cloud's boundary (White & Bai).

    Parameters
    ----------
    depth : number of nested corner-to-corner loops; each is stripped before the next.
    n_corners : angular sectors (>= 8); a sector's corner is its furthest inlier from the centroid.
    c1, c2 : weights of edge length and of inward distance below the envelope (module docstring).
    n_neighbors : k of the kNN graphs and of the density test.
    density_factor : a point is an outlier when its k-th neighbour is further than this times the
        cloud's median k-th neighbour distance; outliers are never corners or path points, so a
        lone far point cannot drag the boundary out. None keeps every point.
    band_factor : only points within ``band_factor * (depth + 1)`` point spacings below the
        envelope polygon enter the graphs (fast at 100k points); None uses every inlier.
    max_inset : a point of depth d lying over ``(d - 1) * max_inset`` point spacings inside the
        first loop is not an interpolant: the deeper path cut a corner through the interior
        there, and merged in it would pull a notch into the spline.

    Fitted: ``points_ (k, 2)`` interpolants ordered along the outermost loop (counter-clockwise),
    ``indices_ (k,)`` into the input, ``depth_paths_`` list of (k_d,) index loops per depth,
    ``corners_ (c, 2)`` first-depth corners, ``corner_indices_`` list per depth,
    ``centroid_ (2,)``, ``outliers_ (m,) bool``, ``spacing_`` mean point spacing.
    A depth is skipped when too few points remain, so ``len(depth_paths_)`` may be < depth.
    """

    def __init__(
        self,
        depth: int = 3,
        n_corners: int = 8,
        c1: float = 1.0,
        c2: float = 1.0,
        n_neighbors: int = 8,
        density_factor: float | None = 4.0,
        band_factor: float | None = 3.0,
        max_inset: float = 2.0,
    ):
        self.depth = depth
        self.n_corners = n_corners
        self.c1 = c1
        self.c2 = c2
        self.n_neighbors = n_neighbors
        self.density_factor = density_factor
        self.band_factor = band_factor
        self.max_inset = max_inset

    def fit(self, uv, geometry: BoundaryGeometry | None = None) -> MultiDepthBoundary:
        """uv : (m, 2) float embedding, any scale; geometry : its `boundary_geometry` with
        this sampler's ``n_neighbors`` and ``density_factor``, if the caller keeps it (it
        does not depend on the depth). Returns self."""
        self._check_params()
        uv = _check_uv(uv, self.n_corners)
        k = int(self.n_neighbors)
        if geometry is None:
            geometry = boundary_geometry(uv, k, self.density_factor)
        outliers, geometry, below = geometry.outliers, geometry.polar, geometry.below
        spacing = geometry.spacing
        candidates = ~outliers
        if self.band_factor is not None:
            candidates &= below <= self.band_factor * (self.depth + 1) * spacing

        remaining = candidates.copy()
        paths, corner_ids = [], []
        for level in range(int(self.depth)):
            ids = np.flatnonzero(remaining)
            if len(ids) < self.n_corners:
                log.debug("boundary depth %d skipped: %d points left", level + 1, len(ids))
                break
            corners = _sector_corners(geometry.theta[ids], geometry.r[ids], self.n_corners)
            if len(corners) < 3:
                break
            inward = geometry.depth_below(ids, remaining)
            outer = inward <= _OUTER * spacing
            loop = _trace_loop(
                uv[ids], geometry.theta[ids], inward, outer, corners, self.c1, self.c2, k,
                _REACH * spacing,
            )
            paths.append(ids[loop])
            corner_ids.append(ids[corners])
            remaining[ids[loop]] = False
        if not paths:
            raise DegenerateCloudError(
                "no boundary loop: the embedded points span fewer than 3 angular sectors"
            )

        self.indices_ = _order_along_first(uv, paths, self.max_inset * geometry.spacing)
        self.points_ = uv[self.indices_]
        self.depth_paths_ = paths
        self.corner_indices_ = corner_ids
        self.corners_ = uv[corner_ids[0]]
        self.centroid_ = geometry.centroid
        self.outliers_ = outliers
        self.spacing_ = geometry.spacing
        log.info(
            "boundary: %d interpolants on %d depths from %d points (%d outliers ignored)",
            len(self.indices_),
            len(paths),
            len(uv),
            int(outliers.sum()),
        )
        return self

    def _check_params(self) -> None:
        if int(self.depth) != self.depth or self.depth < 1:
            raise InvalidInputError(f"depth must be a whole number >= 1, got {self.depth}")
        if int(self.n_corners) != self.n_corners or self.n_corners < 8:
            raise InvalidInputError(f"n_corners must be a whole number >= 8, got {self.n_corners}")
        if not (self.c1 > 0 and self.c2 >= 0):
            raise InvalidInputError(f"need c1 > 0 and c2 >= 0, got c1={self.c1}, c2={self.c2}")
        if int(self.n_neighbors) != self.n_neighbors or self.n_neighbors < 2:
            raise InvalidInputError(f"n_neighbors must be >= 2, got {self.n_neighbors}")
        if self.density_factor is not None and not self.density_factor > 1:
            raise InvalidInputError(f"density_factor must be > 1, got {self.density_factor}")
        if self.band_factor is not None and not self.band_factor > 0:
            raise InvalidInputError(f"band_factor must be > 0, got {self.band_factor}")
        if not self.max_inset > 0:
            raise InvalidInputError(f"max_inset must be > 0, got {self.max_inset}")


class PCABoundary(BaseEstimator):
    """Yumer–Kara baseline: 4 corners at the extremes of the two PCA axes joined by the outermost
    1-point-deep polyline (corner-to-corner paths that hug the outer envelope, ``c2=10``).

    No outlier test: every point may be a corner or on the loop, as in the original method.
    Fitted attributes as `MultiDepthBoundary` (one depth, 4 corners).
    """

    def __init__(self, n_neighbors: int = 8, c2: float = 10.0):
        self.n_neighbors = n_neighbors
        self.c2 = c2

    def fit(self, uv) -> PCABoundary:
        """uv : (m, 2) float embedding. Returns self."""
        if int(self.n_neighbors) != self.n_neighbors or self.n_neighbors < 2:
            raise InvalidInputError(f"n_neighbors must be >= 2, got {self.n_neighbors}")
        uv = _check_uv(uv, 8)
        everything = np.ones(len(uv), dtype=bool)
        geometry = _Polar(uv, everything)
        _, _, axes = np.linalg.svd(uv - geometry.centroid, full_matrices=False)
        along = (uv - geometry.centroid) @ axes.T
        extremes = np.unique(
            [along[:, 0].argmin(), along[:, 1].argmin()]
            + [along[:, 0].argmax(), along[:, 1].argmax()]
        )
        if len(extremes) < 3:
            raise DegenerateCloudError("PCA corners coincide: the points have no 2D spread")
        corners = extremes[np.argsort(geometry.theta[extremes], kind="stable")]
        # The outer band of MultiDepthBoundary's default for one depth (3 × (1 + 1) spacings).
        band = geometry.depth_below(np.arange(len(uv)), everything) <= 6.0 * geometry.spacing
        band[corners] = True
        ids = np.flatnonzero(band)
        local = np.searchsorted(ids, corners)
        inward = geometry.depth_below(ids, band)
        outer = inward <= _OUTER * geometry.spacing
        theta = geometry.theta[ids]
        loop = _trace_loop(uv[ids], theta, inward, outer, local, 1.0, self.c2, self.n_neighbors,
                           _REACH * geometry.spacing)
        loop = ids[loop]
        self.indices_ = loop
        self.points_ = uv[loop]
        self.depth_paths_ = [loop]
        self.corner_indices_ = [corners]
        self.corners_ = uv[corners]
        self.centroid_ = geometry.centroid
        self.outliers_ = np.zeros(len(uv), dtype=bool)
        self.spacing_ = geometry.spacing
        return self


def _check_uv(uv, min_points: int) -> np.ndarray:
    try:
        uv = np.asarray(uv, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"embedding is not numeric: {exc}") from exc
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InvalidInputError(f"expected an embedding of shape (m, 2), got {uv.shape}")
    if not np.isfinite(uv).all():
        raise InvalidInputError("the embedding has NaN or infinite coordinates")
    if len(uv) < min_points:
        raise InvalidInputError(f"{len(uv)} embedded points; the boundary needs {min_points}")
    return uv


class BoundaryGeometry(NamedTuple):
    """What `MultiDepthBoundary` measures of a cloud before its paths, at any depth:
    ``outliers`` (m,) bool, ``polar`` its `_Polar` view of the inliers, ``below`` (m,) each
    point's depth below the inliers' envelope polygon."""

    outliers: np.ndarray
    polar: _Polar
    below: np.ndarray


def boundary_geometry(uv: np.ndarray, n_neighbors: int = 8,
                      density_factor: float | None = 4.0) -> BoundaryGeometry:
    """`BoundaryGeometry` of the embedding ``uv`` (m, 2) (`MultiDepthBoundary`'s parameters):
    a re-mesh at a new depth keeps it rather than query every point's neighbours again."""
    uv = np.asarray(uv, float)
    outliers = np.zeros(len(uv), dtype=bool)
    if density_factor is not None:
        kth = cKDTree(uv).query(uv, k=min(int(n_neighbors) + 1, len(uv)))[0][:, -1]
        typical = np.median(kth)
        if typical > 0:  # else more than half the points are duplicates: keep all
            outliers = kth > density_factor * typical
    polar = _Polar(uv, ~outliers)
    return BoundaryGeometry(outliers, polar, polar.depth_below(np.arange(len(uv)), ~outliers))


class _Polar:
    """Polar view of the cloud about the inliers' centroid, with a fine-sector outer envelope.

    r, theta : (m,) radius and angle (radians) of every point; sector : (m,) fine sector index.
    """

    def __init__(self, uv: np.ndarray, inliers: np.ndarray):
        self.centroid = uv[inliers].mean(axis=0)
        offset = uv - self.centroid
        self.offset = offset
        self.r = np.hypot(offset[:, 0], offset[:, 1])
        self.theta = np.arctan2(offset[:, 1], offset[:, 0])
        n_in = int(inliers.sum())
        self.n_sectors = int(np.clip(np.sqrt(n_in), 16, 1024))
        sector = np.floor((self.theta + np.pi) / (2 * np.pi) * self.n_sectors).astype(np.int64)
        self.sector = np.minimum(sector, self.n_sectors - 1)
        envelope = self.envelope(np.flatnonzero(inliers))
        filled = np.isfinite(envelope)
        area = 0.5 * np.sum(envelope[filled] ** 2) * 2 * np.pi / self.n_sectors
        self.spacing = float(np.sqrt(area / max(n_in, 1))) if area > 0 else float(self.r.max())

    def envelope(self, ids: np.ndarray) -> np.ndarray:
        """(n_sectors,) largest radius of ``ids`` in each fine sector, -inf when empty."""
        out = np.full(self.n_sectors, -np.inf)
        np.maximum.at(out, self.sector[ids], self.r[ids])
        return out

    def depth_below(self, ids: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(len(ids),) perpendicular distance of each point of ``ids`` below the envelope polygon
        of the ``mask`` points, >= 0 (0 on or outside it).

        The envelope polygon joins, in angular order, the outermost ``mask`` point of each
        non-empty fine sector. A point is measured against the polygon edge whose two ends'
        angles bracket its own, perpendicular to that edge: a point on a straight outline that
        the rays from the centroid meet at a grazing angle (the long sides of an elongated
        region) is at depth ~0, where its radial distance below the sector's outermost point
        would be many spacings.
        """
        members = np.flatnonzero(mask)
        # the outermost point of each non-empty fine sector, by angle
        vertex = members[_sector_corners(self.theta[members], self.r[members], self.n_sectors)]
        if len(vertex) < 3:
            return np.zeros(len(ids))
        angle = self.theta[vertex]
        after = np.searchsorted(angle, self.theta[ids], side="right") % len(vertex)
        a = self.offset[vertex[after - 1]]
        b = self.offset[vertex[after]]
        edge = b - a
        rel = self.offset[ids] - a
        cross = edge[:, 0] * rel[:, 1] - edge[:, 1] * rel[:, 0]
        depth = cross / np.maximum(np.hypot(edge[:, 0], edge[:, 1]), 1e-300)
        # counter-clockwise polygon: the inside is to the left of each edge (cross > 0)
        return np.maximum(depth, 0.0)


def _sector_corners(theta: np.ndarray, r: np.ndarray, n_corners: int) -> np.ndarray:
    """Local indices of the furthest point of each non-empty sector, sorted by angle."""
    sector = np.minimum(((theta + np.pi) / (2 * np.pi) * n_corners).astype(np.int64), n_corners - 1)
    order = np.lexsort((-r, sector))
    _, first = np.unique(sector[order], return_index=True)
    corners = order[first]
    return corners[np.argsort(theta[corners], kind="stable")]


def _trace_loop(xy, theta, inward, outer, corners, c1, c2, k, reach) -> np.ndarray:
    """Closed loop (local indices) of shortest paths between consecutive corners, each over the
    points of the wedge between the two corners' angles.

    The graph is first built on the wedge's ``outer`` points only (a thin band below the
    envelope): there the k nearest neighbours of a sparse outer point are other outer points,
    not the denser interior, so the path can follow the outside. If the corners are not
    connected there, the whole wedge is used (k, then 4k neighbours), then a straight segment.
    """
    n_c = len(corners)
    wedge = (np.searchsorted(theta[corners], theta, side="right") - 1) % n_c
    wedge[corners] = np.arange(n_c)
    by_wedge = np.argsort(wedge, kind="stable")
    splits = np.split(by_wedge, np.searchsorted(wedge[by_wedge], np.arange(1, n_c)))
    loop = []
    for i in range(n_c):
        start, end = corners[i], corners[(i + 1) % n_c]
        inner = splits[i][(splits[i] != start) & (splits[i] != end)]
        path = None
        for members, kk in ((inner[outer[inner]], k), (inner, k), (inner, 4 * k)):
            members = np.concatenate([[start], members, [end]])
            path = _dijkstra_path(xy[members], inward[members], c1, c2, kk, reach)
            if path is not None:
                break
        if path is None:
            log.debug("wedge %d of %d is disconnected: straight boundary segment", i, n_c)
            loop.append([start])
        else:
            loop.append(members[path[:-1]])
    return np.concatenate(loop).astype(np.int64)


def _dijkstra_path(points, inward, c1, c2, k, reach) -> np.ndarray | None:
    """Cheapest path from point 0 to the last point, or None: over the symmetric kNN graph plus
    the Delaunay edges no longer than ``reach``. Along the outline the k nearest neighbours of
    a point can all lie inwards, leaving a gap between two outer points that only an inward
    detour crosses; their Delaunay edge bridges it (the length cap keeps concave bays open)."""
    n = len(points)
    k = min(k, n - 1)
    dist, nbr = cKDTree(points).query(points, k=k + 1)
    pairs = np.column_stack([np.repeat(np.arange(n), k), nbr[:, 1:].ravel()])
    if reach > 0 and n >= 4:
        try:
            simplices = Delaunay(points).simplices
        except QhullError:  # collinear or coincident members: the kNN graph alone
            simplices = np.empty((0, 3), dtype=np.int64)
        sides = half_edges(simplices)
        short = np.hypot(*(points[sides[:, 0]] - points[sides[:, 1]]).T) <= reach
        pairs = np.vstack([pairs, sides[short]])
    low, high = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    key = np.unique((low * n + high)[low != high])  # each undirected edge once
    pairs = np.column_stack([key // n, key % n])
    length = np.hypot(*(points[pairs[:, 0]] - points[pairs[:, 1]]).T)
    tail = np.concatenate([pairs[:, 0], pairs[:, 1]])
    head = np.concatenate([pairs[:, 1], pairs[:, 0]])
    step = np.concatenate([length, length])
    # A tiny floor keeps coincident points as edges (csgraph drops explicit zeros).
    weight = c1 * step + c2 * inward[head] + 1e-12 * (1.0 + step.max())
    order = np.argsort(tail * n + head)  # CSR directly: the COO route's checks cost 3x
    indptr = np.concatenate([[0], np.cumsum(np.bincount(tail, minlength=n))])
    graph = csr_matrix((weight[order], head[order], indptr), shape=(n, n))
    cost, pred = dijkstra(graph, directed=True, indices=0, return_predecessors=True)
    if not np.isfinite(cost[n - 1]):
        return None
    path = [n - 1]
    while path[-1] != 0:
        path.append(pred[path[-1]])
    return np.array(path[::-1])


def _order_along_first(uv: np.ndarray, paths: list[np.ndarray], max_inset: float) -> np.ndarray:
    """Indices of all paths sorted by the arc-length position of their projection onto the
    first (outermost) loop, so that deeper points interleave into one consistent closed order.
    A point of depth d further than ``(d - 1) * max_inset`` inside the first loop is left out:
    there the deeper path cut through the interior rather than run beside the first."""
    ref = uv[paths[0]]
    seg = np.roll(ref, -1, axis=0) - ref
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    start = np.concatenate([[0.0], np.cumsum(seg_len)[:-1]])
    position = [start]
    deeper = np.concatenate(paths[1:]) if len(paths) > 1 else np.empty(0, dtype=np.int64)
    if len(deeper):
        p = uv[deeper]
        nearest = cKDTree(ref).query(p)[1]
        options = np.stack([(nearest - 1) % len(ref), nearest])  # (2, q) candidate segments
        rel = p[None] - ref[options]
        d = seg[options]
        t = np.clip((rel * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-300), 0.0, 1.0)
        gap = np.hypot(*(rel - t[..., None] * d).transpose(2, 0, 1))
        pick = gap.argmin(axis=0)
        chosen = options[pick, np.arange(len(p))]
        position.append(start[chosen] + t[pick, np.arange(len(p))] * seg_len[chosen])
        inset = gap[pick, np.arange(len(p))]
    else:
        inset = np.empty(0)
    level = np.concatenate([np.full(len(q), i) for i, q in enumerate(paths)])
    first = len(paths[0])
    keep = np.concatenate([np.ones(first, dtype=bool), inset <= level[first:] * max_inset])
    order = np.lexsort((level[keep], np.concatenate(position)[keep]))
    return np.concatenate(paths)[keep][order]
