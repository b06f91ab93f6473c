"""Checks and repairs of an input point cloud before reconstruction."""

from __future__ import annotations

import logging
import warnings

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .errors import DegenerateCloudError, InvalidInputError, ReconstructionWarning

log = logging.getLogger(__name__)

#: The 85/10/5 split needs a handful of validation points, and the boundary needs >= 8 corners.
MIN_POINTS = 20
#: Points closer to each other than this share of the cloud's diagonal are one point
#: (`merge_duplicates`): a cloud saved twice and merged, its copy moved by round-off (1e-9 mm).
#: Kept twice, every neighbourhood holds half the places it counts and the sheet graph cuts the
#: cloud apart: mug 10k points each doubled 1e-9 to 1e-3 mm apart: 3,550 points left out of
#: every chart against 973, Euler -4 to -8 against 0 (handles), denoise 0.58-0.66 against 0.49.
#: Two distinct samples of a 20k cloud lie this close with odds of about 1e-6. The diagonal
#: leaves far outliers out (`robust_diagonal`): two stray points 1 km off merged a 100 mm cloud
#: into three points.
NEAR_DUPLICATE = 1e-5
#: A point is a twin when its nearest neighbour lies within this share of the median distance
#: to the `TWIN_NEIGHBOUR`-th nearest: a cloud merged with a copy of itself moved by less than
#: the spacing (a re-registered copy) is all twins. Twins are merged when more than
#: `TWIN_SHARE` of the points are: a sample of a surface has 1-2 % twins at σ 0.5 % (mug,
#: chair, 1.6k and 20k) and a noise-free one about 7 % (a Poisson sample of a plane); the mug
#: 10k doubled 0.01-0.2 mm apart (σ 0.83 mm) 40-100 %, Euler -2 to -34 against 0; doubled
#: 0.3 mm apart 16 % (Euler 0), a tenth of its points doubled 20 % (Euler 0).
TWIN = 0.1
TWIN_NEIGHBOUR = 8
TWIN_SHARE = 0.25
#: Points the share of twins is measured on (at random; a cloud's every point beyond).
TWIN_PROBES = 20000


def check_points(points, min_points: int = MIN_POINTS) -> np.ndarray:
    """Validate a cloud and return it as (n, 3) float64, repaired where a sensible result exists.

    Rows with NaN/inf are dropped and duplicates merged (`merge_duplicates`), each with a
    `ReconstructionWarning`.
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

    kept, why = merge_duplicates(array)
    if len(kept) < len(array):
        warnings.warn(f"merged {len(array) - len(kept)} {why}", ReconstructionWarning,
                      stacklevel=2)
        array = array[kept]

    if len(array) < min_points:
        raise InvalidInputError(
            f"{len(array)} usable points; reconstruction needs at least {min_points}"
        )

    centered = array - array.mean(axis=0)
    singular = np.linalg.svd(centered, compute_uv=False)
    if singular[0] == 0 or singular[1] / singular[0] < 1e-6:
        raise DegenerateCloudError("the points are collinear: a surface needs a 2D spread")
    return array


def robust_diagonal(points: np.ndarray) -> float:
    """The diagonal of the box of ``points`` (n, 3) leaving out far outliers: twice the
    interquartile range along each axis (the whole range of points spread evenly; a single
    stray point a kilometre off does not count)."""
    low, high = np.percentile(points, [25, 75], axis=0)
    return float(np.linalg.norm(2 * (high - low)))


def merge_duplicates(points: np.ndarray) -> tuple[np.ndarray, str]:
    """The ``points`` (n, 3) kept, as (k,) sorted indices, and why the others were merged ("":
    none were). Of each group of points chained closer than `NEAR_DUPLICATE` times the
    diagonal (`robust_diagonal`) the first is kept, and so of each group of twins (`TWIN`) when over
    `TWIN_SHARE` of the points have one besides such duplicates."""
    n = len(points)
    tree = cKDTree(points)
    reach = NEAR_DUPLICATE * robust_diagonal(points)
    pairs = [tree.query_pairs(reach, output_type="ndarray")]
    why = f"duplicate points (each within {NEAR_DUPLICATE:g} of the diagonal of another)"
    k = min(TWIN_NEIGHBOUR, n - 1)
    if k >= 2:  # the share of twins, on at most TWIN_PROBES points (1M points: 6 s for all)
        probes = (np.arange(n) if n <= TWIN_PROBES else
                  np.sort(np.random.default_rng(0).choice(n, TWIN_PROBES, replace=False)))
        distance = tree.query(points[probes], k + 1)[0]
        spacing = np.median(distance[:, k])
        share = np.mean((distance[:, 1] < TWIN * spacing) & (distance[:, 1] > reach))
        if share > TWIN_SHARE:
            distance, index = tree.query(points, 2)
            twin = (distance[:, 1] < TWIN * spacing) & (distance[:, 1] > reach)
            pairs.append(np.column_stack([np.flatnonzero(twin), index[twin, 1]]))
            why = (f"points into their twins ({share:.0%} of the points lie within "
                   f"{TWIN:g} spacings of another: a cloud merged with a moved copy of itself?)")
    pairs = np.concatenate(pairs)
    if len(pairs) == 0:
        return np.arange(n), ""
    _, group = connected_components(coo_matrix((np.ones(len(pairs)), pairs.T), shape=(n, n)),
                                    directed=False)
    _, first = np.unique(group, return_index=True)
    return np.sort(first), why


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
