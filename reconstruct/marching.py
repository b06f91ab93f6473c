"""Marching cubes of a grid kept between re-meshes, marched again only round what changed.

scikit-image's Lewiner marching cubes (the closed join's) triangulates each cell from its eight
corner values alone, visits the cells in C order, and creates each vertex when a face first
uses it: on an edge of the grid, placed from the values at its two ends, or inside a cell,
from the cell's eight. So the cells with a changed corner, marched alone, give the faces a
march of the whole grid gives them. Put in place of the old ones in cell order, their vertices
placed as a whole march places them (`_placed`, checked against every whole march) and every
vertex numbered in order of first use, they give that march's vertices and faces bit for bit
(tested). Torus 22k, a 926,000-node grid, a re-mesh that moves two samples: 11-14 ms
instead of 31 ms; the first march, which keeps what the next ones follow, 40 ms. Only the
cells with a changed corner are marched again (skimage's mask), not their whole box: hook 22k,
about 35,000 nodes changed across a 1.6-million-node grid, 41-61 → 26 ms. It keeps
about 20 bytes a node (the float32 grid, and a vertex index per key), against the grid's own
60 or so.

When a march cannot be followed so (a vertex rounded onto a node, which several edges share; a
face in the side of a cell, which two cells share; two corners of a face rounded together,
which skimage merges), or its changes spread over much of the grid (`_MOST`, `_MOST_BOX`), the
whole grid is marched: only the cells the level crosses (`_crossed`), scaled here unless a face
may be degenerate (`marched`), which gives skimage's vertices and faces at about half the
time (sheets 22k, 118,000 faces: 31 -> 21 ms).
"""

from __future__ import annotations

import numpy as np

#: skimage's epsilon in the corner weights that place its vertices (``np.spacing(1.0)``).
_EPSILON = float(np.spacing(1.0))
#: A change of more than this share of the nodes marches the whole grid...
_MOST = 0.05
#: ... and so does one whose box of cells holds more than this share of the grid's nodes:
#: following a march costs nearly as much for its every face as marching the crossed cells
#: (`_crossed`) does. A re-mesh's march (22k, `bench.remesh_atlas`'s changes), followed /
#: whole: the torus's boxes (0.1-0.2 % of its grid, one 14 %) 13-17 / 19-21 ms, the hook's
#: (10 %, 34-36 %) 17-20 / 19-20 ms, the figurine's (61-69 %) median 29.2 / 21.7 ms.
_MOST_BOX = 0.3


def _march(grid: np.ndarray, voxel: float | None = None, mask: np.ndarray | None = None):
    """skimage's march of ``grid`` at 0: with ``voxel``, exactly as the join called it
    (degenerate faces merged); without, the raw vertices (index units) and faces, of the
    cells whose last corner ``mask`` holds (skimage's mask: node n marches the cell n − 1)."""
    from skimage.measure import marching_cubes  # scikit-image: only on the joining path

    if voxel is None:
        vertices, faces, _, _ = marching_cubes(grid, level=0.0, gradient_direction="ascent",
                                               allow_degenerate=True, mask=mask)
    else:
        vertices, faces, _, _ = marching_cubes(grid, level=0.0, spacing=(voxel,) * 3,
                                               gradient_direction="ascent",
                                               allow_degenerate=False, mask=mask)
    return vertices, faces.astype(np.int64)


def _crossed(grid: np.ndarray) -> np.ndarray | None:
    """skimage's mask (as `_march` takes it) of the cells with corners on both sides of the
    level, the only ones that give faces; None when a node lies on it (which side skimage
    counts it on is its own affair). Marching only them gives the same vertices and faces:
    the sheets' 0.6-million-node grid 20.8 -> 17.5 ms, the hook's 1.6 million 22.5 -> 14.4."""
    above = grid > 0
    if np.count_nonzero(above) + np.count_nonzero(grid < 0) != grid.size:
        return None
    some, every = above[1:] | above[:-1], above[1:] & above[:-1]  # over a cell's 8 corners,
    for axis in (1, 2):  # one axis at a time
        high, low = [slice(None)] * 3, [slice(None)] * 3
        high[axis], low[axis] = slice(1, None), slice(None, -1)
        high, low = tuple(high), tuple(low)
        some, every = some[high] | some[low], every[high] & every[low]
    mask = np.zeros(grid.shape, bool)
    mask[1:, 1:, 1:] = some & ~every
    return mask


def marched(grid: np.ndarray, voxel: float, mask: np.ndarray | None = None) -> tuple:
    """``skimage.measure.marching_cubes(grid, 0.0, spacing=(voxel,) * 3, mask=mask,
    gradient_direction="ascent", allow_degenerate=False)``'s vertices (v, 3) float32 and faces
    (f, 3) int64, from a raw march of the cells the level crosses (`_crossed`) scaled here:
    skimage's merging of degenerate faces, a pass over every face and vertex, changes nothing
    but the vertices' type when there are none (a re-mesh's whole march, skimage's / here: the
    sheets' 22k, 118,000 faces, 31 / 21 ms; the hook's, mug's and figurine's 26-30 / 19-23 ms).
    skimage's own when a node lies on the level or a face may be degenerate."""
    grid = np.ascontiguousarray(grid, np.float32)  # what skimage marches (its sides of 0)
    crossed = _crossed_march(grid, voxel, mask)
    if crossed is None:
        return _march(grid, voxel, mask)
    _, vertices, faces = crossed
    return vertices, faces


def _crossed_march(grid: np.ndarray, voxel: float, mask: np.ndarray | None = None):
    """The raw march (index units) of the cells of float32 ``grid`` the level crosses (and
    ``mask`` holds), its vertices scaled as skimage scales them, and its faces: (raw, vertices,
    faces), exactly skimage's march of ``grid``; None when skimage would merge vertices or
    count a node on the level (then only its own march is)."""
    crossed = _crossed(grid)
    if crossed is None:
        return None
    raw, faces = _march(grid, mask=crossed if mask is None else crossed & mask)
    vertices = _scaled(raw, voxel)
    close = _near_nodes(raw, grid.shape)[faces].any(axis=1)
    if not _off_nodes(raw) or _degenerate(vertices, faces[close]):
        return None
    return raw, vertices, faces


class KeptMarch:
    """``skimage.measure.marching_cubes(values, 0.0, spacing=(voxel,) * 3,
    gradient_direction="ascent", allow_degenerate=False)`` of a grid that changes in places
    between calls: the same vertices (v, 3) float32 and faces (f, 3) int64, from the cells
    round the changed nodes when it can (module docstring). ``whole_`` says whether the last
    call marched the whole grid."""

    def __call__(self, values: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
        grid = np.array(values, np.float32, order="C")  # what skimage marches, a copy: kept
        # to compare the next call's with, whose array may be this one changed in place
        kept = self.__dict__.pop("_kept", None)
        result, local = None, True
        if kept is not None and kept["grid"].shape == grid.shape and kept["voxel"] == voxel:
            changed = np.flatnonzero(grid.ravel() != kept["grid"].ravel())
            local = len(changed) <= _MOST * grid.size
            around = _changed_cells(changed, grid.shape) if local else None
            local = local and (around is None
                               or np.prod(around[2] - around[1] + 1) <= _MOST_BOX * grid.size)
            if local and "cells" in kept:
                result = self._again(grid, voxel, kept, around)
        self.whole_ = result is None
        if result is not None:
            return result
        if local:
            return self._whole(grid, voxel)
        # changes all over (a mug's re-mesh: a third of the nodes), or in a large box: the
        # next call likely the same, so only the grid is kept, to count its changes (the
        # crossed cells marched alone, 20 ms; with what a march to follow keeps, 40-55 ms)
        self._kept = {"grid": grid, "voxel": voxel}
        return marched(grid, voxel)

    def _whole(self, grid, voxel):
        crossed = _crossed_march(grid, voxel)
        if crossed is None:
            return _march(grid, voxel)  # as skimage merges such vertices
        raw, vertices, faces = crossed
        keys = _vertex_keys(raw, np.zeros(3, np.int64), grid.shape)  # (every one told apart)
        if np.array_equal(_placed(keys, grid), raw):
            cells = _face_cells(keys, faces, grid.shape)
            if cells is not None and np.all(cells[1:] >= cells[:-1]):
                self._keep(grid, voxel, keys[faces], cells, keys, vertices, faces)
        return vertices.copy(), faces.copy()

    def _again(self, grid, voxel, kept, around):
        """The march from ``kept`` with the cells round the changed nodes (``around``:
        `_changed_cells`) marched again, or None when it cannot be followed exactly."""
        if around is None:
            self._kept = kept
            return kept["vertices"].copy(), kept["faces"].copy()
        nodes, low, high = around
        box = tuple(slice(int(a), int(b) + 2) for a, b in zip(low, high, strict=True))
        marched = _cells_round(nodes - low, high - low + 2)
        try:
            raw, faces = _march(grid[box], mask=marched)
        except (RuntimeError, ValueError):  # no surface in those cells: their faces are gone
            raw, faces = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)
        keys = _vertex_keys(raw, low, grid.shape)
        if keys is None:
            return None
        new_keys = keys[faces]
        new_cells = _face_cells(keys, faces, grid.shape)
        if new_cells is None:
            return None
        old = _not_marched(kept["cells"], marched, low, high, grid.shape)
        cells = kept["cells"][old]
        at = np.searchsorted(cells, new_cells)
        face_keys = np.insert(kept["face_keys"][old], at, new_keys, axis=0)
        cells = np.insert(cells, at, new_cells)
        table, count = kept["table"], len(kept["keys"])
        was = table[face_keys.ravel()]  # each corner's old vertex, if its key still is one
        vertex_keys, first, faces = _numbered(face_keys, table)
        was = was[first]
        was[(was < 0) | (was >= count)] = 0
        same = kept["keys"][was] == vertex_keys
        new_faces = at + np.arange(len(at))
        same[faces[new_faces].ravel()] = False  # on an edge of a cell marched again: placed anew
        vertices = np.empty((len(vertex_keys), 3), np.float32)
        vertices[same] = kept["vertices"][was[same]]
        vertices[~same] = _scaled(_placed(vertex_keys[~same], grid), voxel)
        if _degenerate(vertices, faces[new_faces]):  # the old faces were not
            return None
        self._keep(grid, voxel, face_keys, cells, vertex_keys, vertices, faces, table)
        return vertices.copy(), faces.copy()

    def _keep(self, grid, voxel, face_keys, cells, keys, vertices, faces, table=None):
        """Keep a march to follow: ``cells`` (f,) each face's cell (C order, ascending),
        ``table`` (4 × nodes,) int32 a vertex key's index (stale for keys no longer used:
        checked against ``keys``)."""
        if table is None or len(table) != 4 * grid.size:
            table = np.full(4 * grid.size, -1, np.int32)
        table[keys] = np.arange(len(keys), dtype=np.int32)
        self._kept = {"grid": grid, "voxel": voxel, "face_keys": face_keys, "cells": cells,
                      "keys": keys, "vertices": vertices, "faces": faces, "table": table}


def _changed_cells(changed: np.ndarray, shape) -> tuple | None:
    """The ``changed`` nodes (flat indices in a grid of ``shape``) as (k, 3) indices and the
    box of cells with a changed corner, its first and last cell (3,) each; None for none."""
    if len(changed) == 0:
        return None
    nodes = np.column_stack(np.unravel_index(changed, shape))
    low = np.maximum(nodes.min(axis=0) - 1, 0)
    high = np.minimum(nodes.max(axis=0), np.asarray(shape) - 2)
    return nodes, low, high


def _numbered(face_keys: np.ndarray, table: np.ndarray) -> tuple:
    """The vertex keys in order of first use by ``face_keys`` (f, 3), which corners (3f,)
    use them first, and the faces as indices into them; ``table`` (one entry per key) is
    scratch space (its entries for these keys change)."""
    used = face_keys.ravel()
    corner = np.arange(len(used), dtype=np.int32)
    # each key's first corner: written last, in reverse, as numpy's assignment writes repeated
    # indices in order; checked (each key's entry no later than any of its corners), else by
    # minimum.at (figurine 22k: 266,000 corners, 10 ms for minimum.at, 1.5 for this)
    table[used[::-1]] = corner[::-1]
    at = table[used]
    if not np.all(at <= corner):
        table[used] = len(used)
        np.minimum.at(table, used, corner)
        at = table[used]
    first = at == corner
    index = np.cumsum(first, dtype=np.int64) - 1
    return used[first], first, index[at].reshape(-1, 3)


def _scaled(raw: np.ndarray, voxel: float) -> np.ndarray:
    """Vertices in index units (v, 3) times ``voxel``, rounded as skimage rounds them."""
    return (raw * np.r_[voxel, voxel, voxel]).astype(np.float32)


def _near_nodes(raw: np.ndarray, shape) -> np.ndarray:
    """(v,) bool: the vertices (v, 3; index units) near a grid node or a cell's side along an
    axis where they are not on it: within a margin beyond which two vertices stay apart when
    scaled and rounded to float32 (2⁻²⁴ of a coordinate of up to max(``shape``) nodes; skimage
    merges a face's corners that do not), five times over."""
    margin = 5 * 2.0**-23 * max(shape)
    part = raw - np.floor(raw)
    return np.any((part > 0) & ((part < margin) | (part > 1 - margin)), axis=1)


def _off_nodes(raw: np.ndarray) -> bool:
    """Whether every vertex (v, 3; index units) lies inside its grid edge (one fractional
    coordinate) or cell (three): none rounded onto a node or a cell's side, where vertices of
    several edges may coincide (and `_vertex_keys` cannot tell them apart)."""
    count = np.count_nonzero(raw != np.floor(raw), axis=1)
    return bool(np.all((count == 1) | (count == 3)))


def _degenerate(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether a face has two corners at one place (skimage merges them)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return bool(np.any(np.all(a == b, axis=1) | np.all(a == c, axis=1)
                       | np.all(b == c, axis=1)))


def _vertex_keys(raw: np.ndarray, offset: np.ndarray, shape) -> np.ndarray | None:
    """(v,) int64 key of each vertex (v, 3) of a march (index units, from ``offset`` in a
    grid of ``shape``): 4 × its node + the axis of its edge, or 4 × its cell + 3 for a cell's
    centre vertex; None when one cannot be told (it rounded onto a node or a cell's side)."""
    whole = np.floor(raw)
    fractional = raw != whole
    count = fractional.sum(axis=1)
    if not np.all((count == 1) | (count == 3)):
        return None
    node = whole.astype(np.int64) + offset
    kind = np.where(count == 1, np.argmax(fractional, axis=1), 3)
    return np.ravel_multi_index(tuple(node.T), shape) * 4 + kind


def _placed(keys: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """(k, 3) float32: where skimage places the vertices of ``keys`` (`_vertex_keys`) in
    ``grid`` (index units): on an edge at the node plus w₂ / (w₁ + w₂), w = 1 / (ε + |value|)
    of its ends; a centre vertex at its cell plus the w-weighted mean of the corners, summed in
    skimage's corner order."""
    flat = grid.ravel()
    node, kind = np.divmod(keys, 4)
    out = np.column_stack(np.unravel_index(node, grid.shape)).astype(np.float64)
    stride = np.array([grid.shape[1] * grid.shape[2], grid.shape[2], 1])
    edge = kind < 3
    if edge.any():
        at, axis = node[edge], kind[edge]
        low = 1.0 / (_EPSILON + np.abs(flat[at].astype(np.float64)))
        high = 1.0 / (_EPSILON + np.abs(flat[at + stride[axis]].astype(np.float64)))
        out[np.flatnonzero(edge), axis] += high / (low + high)
    if (~edge).any():
        # skimage's corners v0..v7: (z, y, x) offsets (0,0,0), (0,0,1), (0,1,1), (0,1,0), then z+1
        offsets = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 1], [0, 1, 0],
                            [1, 0, 0], [1, 0, 1], [1, 1, 1], [1, 1, 0]]) @ stride
        w = 1.0 / (_EPSILON + np.abs(flat[node[~edge, None] + offsets].astype(np.float64)))
        total = w[:, 0]
        for k in range(1, 8):
            total = total + w[:, k]
        x = ((w[:, 1] + w[:, 2]) + w[:, 5]) + w[:, 6]
        y = ((w[:, 2] + w[:, 3]) + w[:, 6]) + w[:, 7]
        z = ((w[:, 4] + w[:, 5]) + w[:, 6]) + w[:, 7]
        out[~edge] += np.column_stack([z / total, y / total, x / total])
    return out.astype(np.float32)


def _face_cells(keys: np.ndarray, faces: np.ndarray, shape) -> np.ndarray | None:
    """(f,) the cell (its C-order index) of each of ``faces`` (f, 3) over vertices of ``keys``
    (v,): the one cell that holds its three vertices; None when a face lies in a cell's side
    (two cells hold it)."""
    node, kind = np.divmod(keys, 4)
    edge = kind < 3
    cell = np.zeros(len(faces), np.int64)
    for axis, (stride, size) in enumerate(zip(_strides(shape), shape, strict=True)):
        position = (node // stride) % size  # (v,) each vertex's node (or cell) on this axis
        low = np.maximum(position - (edge & (kind != axis)), 0)  # an edge lies in the cells
        high = np.minimum(position, size - 2)  # on either side across the other two axes
        low = np.maximum(np.maximum(low[faces[:, 0]], low[faces[:, 1]]), low[faces[:, 2]])
        high = np.minimum(np.minimum(high[faces[:, 0]], high[faces[:, 1]]), high[faces[:, 2]])
        if not np.array_equal(low, high):
            return None
        cell = cell * (size - 1) + low
    return cell


def _cells_round(nodes: np.ndarray, shape) -> np.ndarray:
    """skimage's mask (``shape``, bool) of the cells with a corner among ``nodes`` (k, 3): it
    holds node n where one of n − (0|1, 0|1, 0|1) is changed."""
    mask = np.zeros(tuple(int(n) for n in shape), bool)
    mask[tuple(nodes.T)] = True
    for axis in range(3):
        ahead = [slice(None)] * 3
        ahead[axis] = slice(1, None)
        behind = [slice(None)] * 3
        behind[axis] = slice(0, -1)
        mask[tuple(ahead)] |= mask[tuple(behind)].copy()
    return mask


def _not_marched(cells: np.ndarray, marched: np.ndarray, low: np.ndarray, high: np.ndarray,
                 shape) -> np.ndarray:
    """(f,) bool: which ``cells`` (ascending C-order indices) are not among the ``marched``
    ones (`_cells_round`'s mask of the box of cells ``low``..``high``, inclusive)."""
    kept = _outside_box(cells, low, high, shape)
    inside = np.flatnonzero(~kept)
    at = np.column_stack(np.unravel_index(cells[inside], tuple(np.asarray(shape) - 1)))
    kept[inside] = ~marched[tuple((at - low + 1).T)]
    return kept


def _outside_box(cells: np.ndarray, low: np.ndarray, high: np.ndarray, shape) -> np.ndarray:
    """(f,) bool: which ``cells`` (ascending C-order indices) lie outside the box of cells
    ``low``..``high`` (inclusive, (3,)): each of the box's rows of cells is one run of them."""
    sizes = np.asarray(shape) - 1
    z, y = np.meshgrid(np.arange(low[0], high[0] + 1), np.arange(low[1], high[1] + 1),
                       indexing="ij")
    row = (z.ravel() * sizes[1] + y.ravel()) * sizes[2]
    start = np.searchsorted(cells, row + low[2])
    stop = np.searchsorted(cells, row + high[2], side="right")
    outside = np.ones(len(cells), bool)
    change = np.zeros(len(cells) + 1, np.int64)
    np.add.at(change, start, -1)
    np.add.at(change, stop, 1)
    outside[np.cumsum(change[:-1]) < 0] = False
    return outside


def _strides(shape) -> tuple[int, int, int]:
    """The C-order strides (in nodes) of a grid of ``shape``."""
    return shape[1] * shape[2], shape[2], 1
