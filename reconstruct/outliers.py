"""Statistical removal of gross outliers before the embedding (as Open3D's
``remove_statistical_outlier``)."""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from .errors import InvalidInputError

log = logging.getLogger(__name__)


def statistical_outlier_mask(
    points,
    n_neighbors: int = 16,
    std_ratio: float = 3.0,
    min_ratio: float = 0.0,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """Keep-mask of the points whose mean distance to their neighbours is not unusually large.

    For every point the mean euclidean distance to its ``n_neighbors`` nearest other points is
    computed; a point is an outlier when that mean exceeds ``mean + std_ratio * std`` of the means
    over the whole cloud (Open3D's rule) and also exceeds ``min_ratio`` times their median.
    ``min_ratio`` = 0 is Open3D's rule; about 2.5 keeps every true surface point of a clean cloud
    (boundary and corner points reach ~2x the median) and removes only gross outliers.

    points : (n, 3) float, any unit.
    n_neighbors : neighbours per point (clipped to n - 1).
    std_ratio : threshold in standard deviations of the per-point means.
    min_ratio : never remove a point whose mean is below ``min_ratio * median``.
    tree : optional prebuilt `cKDTree` of ``points``.
    Returns (n,) bool, True for the points to keep.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(f"expected points of shape (n, 3), got {points.shape}")
    if n_neighbors < 1:
        raise InvalidInputError(f"n_neighbors must be >= 1, got {n_neighbors}")
    if not std_ratio > 0:
        raise InvalidInputError(f"std_ratio must be > 0, got {std_ratio}")
    if not min_ratio >= 0:
        raise InvalidInputError(f"min_ratio must be >= 0, got {min_ratio}")
    n = len(points)
    k = min(int(n_neighbors), n - 1)
    if k < 1:
        return np.ones(n, dtype=bool)
    tree = cKDTree(points) if tree is None else tree
    # k + 1 because the nearest hit of a point is normally the point itself (distance 0). With
    # exact duplicates the duplicate may come first instead; both have distance 0, so dropping
    # the first column is correct either way.
    distances, _ = tree.query(points, k=k + 1)
    mean_distance = distances[:, 1:].mean(axis=1)
    threshold = max(
        mean_distance.mean() + std_ratio * mean_distance.std(),
        min_ratio * np.median(mean_distance),
    )
    keep = mean_distance <= threshold
    n_removed = int(n - keep.sum())
    if n_removed:
        log.debug("statistical outliers: %d of %d points beyond %.4g", n_removed, n, threshold)
    return keep
