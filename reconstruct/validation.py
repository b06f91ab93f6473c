"""Checks and repairs of an input point cloud before reconstruction."""

from __future__ import annotations

import logging
import warnings

import numpy as np

from .errors import DegenerateCloudError, InvalidInputError, ReconstructionWarning

log = logging.getLogger(__name__)

#: The 85/10/5 split needs a handful of validation points, and the boundary needs >= 8 corners.
MIN_POINTS = 20


def check_points(points, min_points: int = MIN_POINTS) -> np.ndarray:
    """Validate a cloud and return it as (n, 3) float64, repaired where a sensible result exists.

    Rows with NaN/inf are dropped and exact duplicates merged (each with a `ReconstructionWarning`).
    Raises `InvalidInputError` for a wrong shape, an empty cloud or too few points, and
    `DegenerateCloudError` for a collinear cloud.
    """
    try:
        array = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"points are not numeric: {exc}") from exc
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidInputError(f"expected points of shape (n, 3), got {array.shape}")
    if len(array) == 0:
        raise InvalidInputError("the point cloud is empty")

    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        n_bad = int((~finite).sum())
        if n_bad == len(array):
            raise InvalidInputError(f"all {n_bad} points have NaN or infinite coordinates")
        warnings.warn(
            f"dropped {n_bad} of {len(array)} points with NaN or infinite coordinates",
            ReconstructionWarning,
            stacklevel=2,
        )
        array = array[finite]

    unique, first_index = np.unique(array, axis=0, return_index=True)
    if len(unique) < len(array):
        warnings.warn(
            f"merged {len(array) - len(unique)} duplicate points",
            ReconstructionWarning,
            stacklevel=2,
        )
        array = array[np.sort(first_index)]

    if len(array) < min_points:
        raise InvalidInputError(
            f"{len(array)} usable points; reconstruction needs at least {min_points}"
        )

    centered = array - array.mean(axis=0)
    singular = np.linalg.svd(centered, compute_uv=False)
    if singular[0] == 0 or singular[1] / singular[0] < 1e-6:
        raise DegenerateCloudError("the points are collinear: a surface needs a 2D spread")
    return array


#: The fewest points a ``max_points`` may keep.
MIN_MAX_POINTS = 100


def check_max_points(limit) -> None:
    """Refuse a ``max_points`` (`InvalidInputError`) that is neither None nor a whole number of
    at least `MIN_MAX_POINTS`."""
    if limit is not None and not (isinstance(limit, (int, np.integer))
                                  and not isinstance(limit, bool) and limit >= MIN_MAX_POINTS):
        raise InvalidInputError(f"max_points must be a whole number >= {MIN_MAX_POINTS} or "
                                f"None, got {limit!r}")


def random_subset(points: np.ndarray, limit: int | None, random_state) -> np.ndarray:
    """The rows (m, 3) of ``points`` (n, 3) a fit takes: all when ``limit`` is None or not
    below n, else a random ``limit`` of them, in their order. Seeded by ``random_state`` when it
    is a whole number, else by 0: the same rows at every call (a fit takes up what `embed`
    computed of them). A ``limit`` `check_max_points` refuses raises `InvalidInputError`."""
    check_max_points(limit)
    if limit is None or len(points) <= limit:
        return points
    seed = random_state if isinstance(random_state, (int, np.integer)) else 0
    keep = np.random.default_rng(seed).choice(len(points), int(limit), replace=False)
    return points[np.sort(keep)]
