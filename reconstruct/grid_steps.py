"""The steps of a closed join's signed grid (`reconstruct.closed_grid.ClosedSDF`), on a whole
grid or a box of it: distances to the occupied cells, the free pockets and their votes on
which side they lie, and the boxes of nodes round what changed.
"""

from __future__ import annotations

import cc3d
import numpy as np
from scipy import ndimage

from .kdtree import QUERY_THREADS, PointTree

#: About as many nodes of one enclosed pocket vote on its side (`exterior_of`), evenly taken:
#: its share in front to about ±1 %. All of a torus's inside (181,604 nodes) took 0.8 s of a
#: 1.9 s re-mesh.
VOTERS = 4096
#: A voter of an enclosed pocket is in front when the planes of its nearest sample and of every
#: sample within this many voxels farther (of its `VOTE_NEIGHBOURS` nearest) put it there: a
#: chart spanning a junction (mug 20k seed 1: the wall's across the handle's upper root, facing
#: +x) is nearest to the free core of the handle there, 3.1-3.4 voxels in front of it, while
#: the handle's faces 0.6-0.8 voxels farther put it 3.3-4 voxels behind theirs. The nearest
#: alone voted that core outside, the closing turned the root's cross-section outside and
#: the handle was cut (Euler 2 against 0); with this, 0 (0.5 voxel or 8 neighbours: still 2).
#: bench.atlas 20k seed 0 unchanged but for sheets (Chamfer 0.5064 / 0.5069).
VOTE_MARGIN = 1.0
VOTE_NEIGHBOURS = 16


def cell_reach(distance):
    """Nodes from a cell (as `squared_distance` counts them from a True one) within which every
    node within ``distance`` voxels (float or array) of a point in that cell lies: the
    distance and the cell's diagonal, √3, and a hair so that rounding leaves none out."""
    return distance + np.sqrt(3.0) + 1e-9


def squared_distance(targets: np.ndarray, radius: float) -> np.ndarray:
    """(shape) unsigned ints: each node's squared Euclidean distance, in nodes, to the nearest
    True node of ``targets``, exact where it is at most ``radius``² and above it (not exact)
    elsewhere. Three separable passes of minima over the shifts of up to ⌊radius⌋ nodes (no
    farther shift along one axis can be within ``radius``), in the narrowest unsigned type that
    holds them (uint8 up to radius 7: a 0.9-million-node grid at radius 7 took 28 ms in int32,
    6 ms in uint8). scipy's exact transform of the whole grid, ``distance_transform_edt(~targets)``,
    gives the same within ``radius``; the join only needs it within a few voxels, and this took a
    fifth to a third of its time on a 7-million-node grid (radius 3 and 6)."""
    reach = int(np.floor(radius))
    far = 3 * (reach + 1) ** 2  # farther than radius² and than any sum of in-range
    dtype = next(t for t in (np.uint8, np.uint16, np.uint32)
                 if far + reach * reach <= np.iinfo(t).max)
    squared = np.where(targets, dtype(0), dtype(far))
    for axis in range(squared.ndim):
        nearest = squared.copy()
        for shift in range(1, min(reach, squared.shape[axis] - 1) + 1):
            low, high = [slice(None)] * squared.ndim, [slice(None)] * squared.ndim
            low[axis], high[axis] = slice(0, -shift), slice(shift, None)
            low, high = tuple(low), tuple(high)
            step = dtype(shift * shift)
            np.minimum(nearest[high], squared[low] + step, out=nearest[high])
            np.minimum(nearest[low], squared[high] + step, out=nearest[low])
        squared = nearest
    return squared


def grey_opening3(values: np.ndarray) -> np.ndarray:
    """``ndimage.grey_opening(values, size=3)`` (its default border, 'reflect') node for node:
    the minimum, then the maximum, of each node's 3-node neighbourhood, one axis at a time,
    from pairwise extremes (a 0.9-million-node grid: 33 ms in scipy, 7 ms here)."""
    return _extreme3(_extreme3(values, np.minimum), np.maximum)


def _extreme3(values: np.ndarray, extreme) -> np.ndarray:
    """Each node's ``extreme`` (np.minimum or np.maximum) over its 3-node neighbourhood along
    every axis in turn; a neighbour beyond the border is the node itself."""
    for axis in range(values.ndim):
        if values.shape[axis] < 2:
            continue

        def along(part, axis=axis, ndim=values.ndim):
            index = [slice(None)] * ndim
            index[axis] = part
            return tuple(index)
        pairs = extreme(values[along(slice(0, -1))], values[along(slice(1, None))])  # i, i + 1
        result = np.empty_like(values)
        result[along(slice(0, 1))] = pairs[along(slice(0, 1))]
        result[along(slice(-1, None))] = pairs[along(slice(-1, None))]
        extreme(pairs[along(slice(0, -1))], pairs[along(slice(1, None))],
                out=result[along(slice(1, -1))])
        values = result
    return values


def farther_than(targets: np.ndarray, radius: float) -> np.ndarray:
    """(shape) bool: the nodes farther than ``radius`` nodes from every True node of
    ``targets``, as ``distance_transform_edt(~targets) > radius`` says (the same square roots
    compared)."""
    limit = int(np.floor(radius * radius))  # the largest whole n with √n ≤ radius
    while np.sqrt(limit + 1) <= radius:
        limit += 1
    while limit >= 0 and np.sqrt(limit) > radius:
        limit -= 1
    return squared_distance(targets, radius) > limit


def grid_box(samples: np.ndarray, voxel: float, pad: float):
    """Origin (3,) and shape (3,) of a grid of spacing ``voxel`` round ``samples`` (m, 3)."""
    origin = samples.min(axis=0) - pad * voxel
    shape = np.ceil((samples.max(axis=0) + pad * voxel - origin) / voxel).astype(int) + 1
    return origin, shape


def occupancy(samples, extra, origin, shape, voxel: float) -> np.ndarray:
    """(shape) bool: the grid's cells holding a sample (m, 3) or an ``extra`` point (p, 3;
    those outside the grid ignored)."""
    occupied = np.zeros(tuple(shape), bool)
    occupied[tuple(np.floor((samples - origin) / voxel + 0.5).astype(int).T)] = True
    if extra is not None and len(extra):
        nodes = np.floor((np.asarray(extra, float) - origin) / voxel + 0.5).astype(int)
        occupied[tuple(nodes[np.all((nodes >= 0) & (nodes < shape), axis=1)].T)] = True
    return occupied


def exterior_of(free, origin, voxel: float, samples=None, normals=None, tree=None):
    """(shape) bool: the ``free`` nodes outside the sampled surface.

    The free nodes connected to the grid's border are exterior. A free pocket enclosed by the
    samples (the inside of a closed object, or a concave nook the band closed off) is exterior
    when the nearest samples' tangent planes, oriented by ``normals`` (m, 3), put most of its
    nodes in front (without normals: never). ``tree``: a `kdtree.PointTree` of ``samples``
    (m, 3)."""
    pockets = free_pockets(free)
    front = None
    if normals is not None and pockets[2] is not None:
        tree = PointTree(samples) if tree is None else tree
        front = voter_sides(origin + voxel * pockets[2][0], samples, normals, tree, voxel)[1]
    return pockets_outside(pockets, front)[pockets[0]] & free


def free_pockets(free: np.ndarray) -> tuple:
    """The connected pieces of the ``free`` nodes: (pieces (shape) int, whether each piece
    (count + 1,; 0: none) touches the grid's border, voters: (nodes (g, 3), piece (g,), flat
    index (g,)) of the enclosed pieces (`pocket_voters`), or None)."""
    # cc3d labels as scipy's ndimage.label (6-connected, numbered in C order of first node:
    # the same labels, tested) in a fifth of the time (figurine 22k, 1.2 million nodes: 9-14
    # ms against 2.2); the whole grid is labelled again whenever a node flips
    pieces, count = cc3d.connected_components(np.ascontiguousarray(free), connectivity=6,
                                              return_N=True)
    pieces = pieces.astype(np.int32, copy=False)
    faces = [pieces[0], pieces[-1], pieces[:, 0], pieces[:, -1], pieces[:, :, 0],
             pieces[:, :, -1]]
    border = np.zeros(count + 1, bool)
    border[np.concatenate([f.ravel() for f in faces])] = True
    border[0] = False
    voters = None
    if not border[1:].all():  # an enclosed piece
        enclosed = ~border
        enclosed[0] = False
        flat = np.flatnonzero(enclosed[pieces.ravel()])
        voters = pocket_voters(flat, pieces.ravel()[flat], free.shape)
    return pieces, border, voters


def voter_sides(at, samples, normals, tree: PointTree,
                voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """For the voters at ``at`` (g, 3): the distance (g,) to their nearest sample and whether
    they lie in front (g,) of its tangent plane and of those of the samples within
    `VOTE_MARGIN` ``voxel`` of it."""
    distance, nearest = tree.query(at, k=min(VOTE_NEIGHBOURS, len(samples)),
                                   workers=QUERY_THREADS)
    distance, nearest = distance.reshape(len(at), -1), nearest.reshape(len(at), -1)
    ahead = np.einsum("gki,gki->gk", at[:, None, :] - samples[nearest],
                      np.asarray(normals, float)[nearest])
    near = distance <= distance[:, :1] + VOTE_MARGIN * voxel
    return distance[:, 0], np.all((ahead > 0) | ~near, axis=1)


def pockets_outside(pockets: tuple, front=None) -> np.ndarray:
    """(count + 1,) bool: which of the `free_pockets` are outside: those touching the border,
    and the enclosed ones whose voters mostly lie in ``front`` (g,) of their nearest samples
    (`voter_sides`; None: no enclosed one)."""
    _, border, voters = pockets
    if front is None or voters is None:
        return border.copy()
    label = voters[1]
    share = np.bincount(label, front, minlength=len(border)) / np.maximum(
        np.bincount(label, minlength=len(border)), 1)
    return border | (share > 0.5)


def pocket_voters(flat: np.ndarray, label: np.ndarray, shape) -> tuple:
    """About `VOTERS` of the nodes ``flat`` ((g,) ascending flat indices into a grid of
    ``shape``) of each pocket ``label`` (g,), spread evenly and chosen by their place alone
    (a hash of the index), so that a node stays a voter while its pocket changes elsewhere
    (its vote is kept between updates); returns (nodes (k, 3), label (k,), flat (k,)) of
    those, in grid order."""
    step = -(-np.bincount(label) // VOTERS)
    if step.max(initial=1) > 1:
        chosen = _spread(flat) % step[label].astype(np.uint64) == 0
        flat, label = flat[chosen], label[chosen]
    return np.column_stack(np.unravel_index(flat, tuple(shape))), label, flat


def _spread(flat: np.ndarray) -> np.ndarray:
    """(g,) uint64: the indices ``flat`` scattered (Fibonacci hashing, the top 32 bits), so
    that taking those divisible by a step takes nodes evenly, not rows or planes of them."""
    return (flat.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(32)


def boxes_round(flat: np.ndarray, shape, margin: int) -> list[tuple[slice, ...]]:
    """Boxes (3 slices each) covering the grid nodes ``flat`` grown by ``margin`` voxels and
    clipped to the grid ``shape``: one per cluster of nodes in touching blocks of 2 ``margin``
    voxels."""
    if len(flat) == 0:
        return []
    cells = np.column_stack(np.unravel_index(flat, tuple(shape)))
    coarse = cells // (2 * max(int(margin), 1))
    blocks = np.zeros(tuple(coarse.max(axis=0) + 1), bool)
    blocks[tuple(coarse.T)] = True
    pieces, count = ndimage.label(blocks, structure=np.ones((3, 3, 3), bool))
    piece = pieces[tuple(coarse.T)] - 1
    low = np.full((count, 3), np.iinfo(np.int64).max)
    high = np.full((count, 3), -1)
    np.minimum.at(low, piece, cells)
    np.maximum.at(high, piece, cells)
    low = np.maximum(low - margin, 0)
    high = np.minimum(high + margin + 1, np.asarray(shape))
    return [tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
            for lo, hi in zip(low, high, strict=True)]


def grown(box: tuple[slice, ...], margin: int, shape) -> tuple[tuple[slice, ...], tuple]:
    """``box`` grown by ``margin`` (clipped to ``shape``), and ``box`` within the grown one."""
    outer = tuple(slice(max(s.start - margin, 0), min(s.stop + margin, int(n)))
                  for s, n in zip(box, shape, strict=True))
    inner = tuple(slice(s.start - o.start, s.stop - o.start)
                  for s, o in zip(box, outer, strict=True))
    return outer, inner


def flat_of(box: tuple[slice, ...], mask: np.ndarray, shape) -> np.ndarray:
    """Flat grid indices of the nodes of ``box`` where ``mask`` (the box's shape) holds."""
    local = np.argwhere(mask) + np.array([s.start for s in box])
    return np.ravel_multi_index(tuple(local.T), tuple(shape))
