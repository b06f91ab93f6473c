"""Aligning a new embedding of a surface to an earlier one, so that an earlier network can go on.

When the same surface is fitted again after more points arrived (a scan's patch after more
views), its new 2D embedding is an arbitrary rotation, reflection and shift of the earlier one.
The points both clouds share pair the two embeddings, and an orthogonal Procrustes fit (no scale)
maps the new one onto the earlier one: the earlier network then sees familiar inputs and is
fine-tuned instead of searched again (`SurfaceReconstructor.fit(points, warm_start=...)`).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from .errors import WarmStartRefused

log = logging.getLogger(__name__)

#: A warm start needs this share of the new points matched to the earlier fit's points …
MIN_SHARED = 0.15
#: … and an alignment residual below this share of the earlier embedding's extent.
MAX_ALIGN_ERROR = 0.08


def shared_points(previous_points, points, tolerance: float):
    """Index pairs (into ``points`` (n, 3), into ``previous_points`` (m, 3)) of the points
    within ``tolerance`` of an earlier one (the nearest)."""
    distance, index = cKDTree(previous_points).query(points, distance_upper_bound=tolerance)
    mine = np.flatnonzero(np.isfinite(distance))
    return mine, index[mine]


def align_embedding(new_uv, old_uv):
    """Orthogonal Procrustes (reflection allowed, no scale) of paired 2D points.

    new_uv, old_uv : (k, 2) the same points in the two embeddings.
    Returns (apply: (n, 2) → (n, 2), RMS residual of the pairs in ``old_uv`` units).
    """
    a_mean, b_mean = new_uv.mean(axis=0), old_uv.mean(axis=0)
    u, _, vt = np.linalg.svd((new_uv - a_mean).T @ (old_uv - b_mean))
    rotation = u @ vt

    def apply(uv):
        return (np.asarray(uv) - a_mean) @ rotation + b_mean

    residual = float(np.sqrt(np.mean(np.sum((apply(new_uv) - old_uv) ** 2, axis=1))))
    return apply, residual


def align_to(uv, points, previous_uv, previous_points, tolerance: float) -> np.ndarray:
    """(n, 2) ``uv`` (the embedding of (n, 3) ``points``) moved onto ``previous_uv`` (of
    ``previous_points``) through the points within ``tolerance`` of an earlier one.

    Raises `WarmStartRefused` when fewer than ``MIN_SHARED`` of the points (and 20) are shared
    or the residual exceeds ``MAX_ALIGN_ERROR`` of the earlier embedding's extent."""
    mine, theirs = shared_points(previous_points, points, tolerance)
    if len(mine) < max(20, MIN_SHARED * len(points)):
        log.debug("warm start refused: %d of %d points shared", len(mine), len(points))
        raise WarmStartRefused(f"{len(mine)} of {len(points)} points shared with the earlier fit")
    apply, residual = align_embedding(uv[mine], previous_uv[theirs])
    extent = float(np.ptp(previous_uv, axis=0).max())
    if residual > MAX_ALIGN_ERROR * extent:
        log.debug("warm start refused: alignment residual %.3g of extent %.3g", residual, extent)
        raise WarmStartRefused(f"alignment residual {residual:.3g} of extent {extent:.3g}")
    return apply(uv)
