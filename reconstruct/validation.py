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
#: Points closer to each other than this share of the cloud's diagonal (`robust_diagonal`) are
#: one point (`merge_duplicates`): exact duplicates, and copies moved by round-off (1e-9 mm).
NEAR_DUPLICATE = 1e-9
#: A point is a twin when its nearest neighbour lies nearer than this share of its second
#: nearest: it stands in a pair apart from the others. A cloud merged with a copy of itself
#: moved by less than the spacing (saved twice, or re-registered) is all twins; kept twice, the
#: sheet graph cuts it apart: the mug of 10k points (σ 0.83 mm, spacing 1.4 mm), each doubled
#: with 1e-9 to 0.2 mm of jitter along each axis, had 3,550 points left out of every chart
#: against 973 and Euler -2 to -34 against 0 (handles). A sample of a surface has few twins
#: whatever its density, as (d1 / d2)² of a Poisson sample of a plane is uniform: 4 %, 1 % for
#: the mug at σ 0.5 %; points thrown at random along lines 19 %. The mug doubled with 0.2 mm of
#: jitter has 43 %, with 0.3 mm 20 % (and is meshed with its genus as it is).
TWIN = 0.2
#: Twins are merged when more than this share of the points are twins (two interleaved sets of
#: evenly spaced stripes, as from two cameras, have 32 %).
TWIN_SHARE = 0.4
#: In a cloud of twins, mutual nearest neighbours nearer than this share of their next are
#: merged: a copy moved 0.1 of the spacing often has a neighbour of its original within five
#: times as far (a plane of 3,000 points doubled 0.1 spacings apart kept 3,993 points with
#: `TWIN` alone, and its sheet graph fell into 74 pieces; 3,092 and one piece with this).
TWIN_PAIR = 0.5
#: ... and nearer than this many times the twins' median distance: the copy's offset, not a
#: pair of the original's own points (a plane of 10k points, 41 % of it doubled, lost 9 % of
#: the points never doubled without it).
TWIN_OFFSETS = 4.0
#: Passes of `merge_duplicates` at most (each removes a share of the points; a contrived cloud
#: whose interquartile range each removal widens took 198).
MERGE_PASSES = 10
#: Fewer points than this do not tell twins from chance.
TWIN_MIN_POINTS = 100
#: Points the share of twins is measured on, at random (its standard error 1.1 % at 40 %): a
#: fit checks its cloud up to four times, and the 20k mug's 3 nearest of every point took 33 of
#: the check's 59 ms.
TWIN_PROBES = 2000


#: The largest coordinate a cloud may hold: beyond it a squared distance overflows float64.
MAX_COORDINATE = 1e150


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

    largest = float(np.abs(array).max())
    if largest > MAX_COORDINATE:  # squared distances overflow to inf: every point an outlier
        raise InvalidInputError(f"coordinates as large as {largest:.3g} (beyond "
                                f"±{MAX_COORDINATE:g}): distances between the points overflow; "
                                "rescale the cloud")
    kept, why = merge_duplicates(array)
    if len(kept) < len(array):
        warnings.warn(f"merged {len(array) - len(kept)} {why}", ReconstructionWarning,
                      stacklevel=2)
        array = array[kept]

    if len(array) < min_points:
        raise InvalidInputError(
            f"{len(array)} usable points; reconstruction needs at least {min_points}"
        )

    check_spread(array)
    return array


def check_spread(points: np.ndarray) -> None:
    """`DegenerateCloudError` when the bulk of ``points`` (n, 3) is collinear: the points
    within twice the interquartile range of the middle along each axis (a far stray point, a
    depth camera's invalid value 1e9 away, outweighed a whole sphere's spread)."""
    low, high = np.percentile(points, [25, 75], axis=0)
    bulk = points[np.all(np.abs(points - (low + high) / 2) <= 2 * (high - low), axis=1)]
    if len(bulk) < 3:
        bulk = points
    singular = np.linalg.svd(bulk - bulk.mean(axis=0), compute_uv=False)
    if singular[0] == 0 or singular[1] / singular[0] < 1e-6:
        raise DegenerateCloudError("the points are collinear: a surface needs a 2D spread")


def robust_diagonal(points: np.ndarray) -> float:
    """The diagonal of the box of ``points`` (n, 3) leaving out far outliers: twice the
    interquartile range along each axis (the whole range of points spread evenly; a single
    stray point a kilometre off does not count)."""
    low, high = np.percentile(points, [25, 75], axis=0)
    return float(np.linalg.norm(2 * (high - low)))


def merge_duplicates(points: np.ndarray) -> tuple[np.ndarray, str]:
    """The ``points`` (n, 3) kept, as (k,) sorted indices, and what was merged ("": nothing):
    the first of each group of points within `NEAR_DUPLICATE` of one another, and of each pair
    of twins when they are over `TWIN_SHARE` of the points (`_merged_once`); again until
    nothing merges (at most `MERGE_PASSES` times), so that the points kept give themselves
    back."""
    _, first = np.unique(points, axis=0, return_index=True)  # exact: query_pairs would list
    kept = np.sort(first)  # every pair of a large group (30,000 invalid pixels at the origin)
    said = ["duplicate points"] if len(kept) < len(points) else []
    for _ in range(MERGE_PASSES):
        step, what = _merged_once(points[kept])
        if len(step) == len(kept):
            break
        kept, said = kept[step], said + [what]
    return kept, " and ".join(dict.fromkeys(said))


def _merged_once(points: np.ndarray) -> tuple[np.ndarray, str]:
    """One pass of `merge_duplicates` over distinct ``points`` (n, 3): (k,) sorted indices
    kept, and what was merged. When over `TWIN_SHARE` of the points are twins (`TWIN`), each
    pair of mutual nearest neighbours nearer than `TWIN_PAIR` times their next and
    `TWIN_OFFSETS` times the twins' median distance is merged: also the copies that a
    neighbour of the original stands close to."""
    n = len(points)
    size = robust_diagonal(points) if np.abs(points).max(initial=0.0) < 1e150 else np.inf
    if not 1e-150 < size < np.inf:  # squared distances overflow or underflow: not compared
        return np.arange(n), ""
    tree = cKDTree(points)
    reach = NEAR_DUPLICATE * size
    pairs = [tree.query_pairs(reach, output_type="ndarray")]
    what = "duplicate points"
    if n >= TWIN_MIN_POINTS:
        probes = (slice(None) if n <= TWIN_PROBES else
                  np.sort(np.random.default_rng(0).choice(n, TWIN_PROBES, replace=False)))
        distance, index = tree.query(points[probes], 3)
        share = np.mean(_nearer(distance, reach, TWIN))
        if share > TWIN_SHARE:
            if n > TWIN_PROBES:  # every point's, now
                distance, index = tree.query(points, 3)
            partner = index[:, 1]
            offset = TWIN_OFFSETS * np.median(distance[_nearer(distance, reach, TWIN), 1])
            pair = (_nearer(distance, reach, TWIN_PAIR) & (distance[:, 1] <= offset)
                    & (partner[partner] == np.arange(n)))
            pairs.append(np.column_stack([np.flatnonzero(pair), partner[pair]]))
            what = (f"points into their twins ({share:.0%} of the points have a neighbour "
                    f"{1 / TWIN:g} times nearer than their next: a surface sampled twice, as by "
                    f"a cloud merged with a moved copy of itself, or a flat face averaged into "
                    f"two voxel layers)")
    pairs = np.concatenate(pairs)
    if len(pairs) == 0:
        return np.arange(n), ""
    _, group = connected_components(coo_matrix((np.ones(len(pairs)), pairs.T), shape=(n, n)),
                                    directed=False)
    _, first = np.unique(group, return_index=True)
    return np.sort(first), what


def _nearer(distance: np.ndarray, reach: float, share: float) -> np.ndarray:
    """(q,) bool: points whose nearest (``distance`` (q, 3) to themselves and their two
    nearest) lies farther than ``reach`` (the duplicates') and nearer than ``share`` times the
    second."""
    return (distance[:, 1] > reach) & (distance[:, 1] < share * distance[:, 2])


#: The fewest points a ``max_points`` may keep.
MIN_MAX_POINTS = 100
#: The points an atlas charts of a denser cloud (`AtlasReconstructor`'s ``max_points``,
#: `SurfaceReconstructor`'s ``atlas_points``): at scanner noise more add noise to smooth
#: objects, but detail to finely detailed ones. At 100k points, σ 0.5 %, seed 0, the atlas
#: alone: the scanned dragon (`bench.scanned`) Chamfer-L1 0.348 on 20,000, 0.297 on 30,000,
#: 0.274 on 40,000, 0.254 on 50,000 (38 s, 1.6 GB), 0.403 on all (its join's grid finer than
#: the noise); the mug 0.223 on 20,000, 0.260 on 40,000, 0.240 on 50,000.
ATLAS_POINTS = 20_000


#: The finest join grid an atlas lays, in median point spacings: at 0.1 it holds 125 times
#: the nodes of the default 0.5 (a 20k cloud's 0.6-1.2 million: about 100 million, gigabytes);
#: a finer one overflowed its box after the charts' fit (1e-300: "negative dimensions").
MIN_VOXEL = 0.1


def check_voxel(voxel) -> None:
    """Refuse a join ``voxel`` (`InvalidInputError`) that is not a number from `MIN_VOXEL`."""
    if isinstance(voxel, (bool, np.bool_)) or not (
            isinstance(voxel, (int, float, np.number)) and MIN_VOXEL <= voxel < np.inf):
        raise InvalidInputError(f"voxel must be a number >= {MIN_VOXEL} (median point "
                                f"spacings; finer grids hold too many nodes), got {voxel!r}")


def check_max_points(limit, name: str = "max_points") -> None:
    """Refuse a ``max_points`` (`InvalidInputError`, naming it ``name``) that is neither None nor
    a whole number of at least `MIN_MAX_POINTS`."""
    if limit is not None and not (isinstance(limit, (int, np.integer))
                                  and not isinstance(limit, bool) and limit >= MIN_MAX_POINTS):
        raise InvalidInputError(f"{name} must be a whole number >= {MIN_MAX_POINTS} or "
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
