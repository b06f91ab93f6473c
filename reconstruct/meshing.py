"""Meshing in the 2D parameter domain: a regular grid re-sampled inside the boundary polygon, the
boundary's own points as vertices, Delaunay, triangles whose centroid is outside removed.

The grid's full cells are split into two triangles each directly (a regular grid's Delaunay
triangulation, up to the arbitrary diagonal of co-circular points); only the band between the
grid and the boundary goes through scipy's Delaunay. That keeps re-meshing fast (a 50k-vertex
mesh in tens of milliseconds instead of seconds). If the band does not stitch cleanly onto the
grid the whole set is triangulated by Delaunay instead, so the result is always the paper's.
"""

from __future__ import annotations

import numpy as np
import shapely
from scipy.spatial import Delaunay

from .errors import FitError
from .mesh_edges import face_centres, half_edges

#: Most nodes the box of a chart's 2D grid may hold: a grid spacing far below the points' (or
#: an outline extended far beyond them) would take the machine's memory (a washer chart at
#: spacing 1e-6: 1.5e8 nodes, 2.25 GiB for their coordinates alone, and more after).
MAX_GRID_NODES = 20_000_000


def default_spacing(polygon: np.ndarray, n_points: int) -> float:
    """Grid spacing that gives about as many mesh vertices as the cloud has points.

    polygon : (p, 2) closed boundary polygon. n_points : cloud size.
    """
    area = abs(signed_area(polygon))
    return float(np.sqrt(area / max(int(n_points), 1)))


def sample_ring(polygon: np.ndarray, spacing: float) -> np.ndarray:
    """(q, 2) points along the closed ``polygon (p, 2)`` about ``spacing`` apart in arc length,
    q >= 3, the first at the polygon's first vertex."""
    steps = np.hypot(*np.diff(polygon, axis=0).T)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    q = max(3, int(round(arc[-1] / spacing)))
    at = np.linspace(0.0, arc[-1], q, endpoint=False)
    return np.column_stack([np.interp(at, arc, polygon[:, 0]), np.interp(at, arc, polygon[:, 1])])


def mesh_inside(
    polygon: np.ndarray, boundary_points: np.ndarray, spacing: float, lattice: bool = False,
    grid: tuple | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate the region inside ``polygon``.

    polygon : (p, 2) dense closed polygon of the boundary spline.
    boundary_points : (b, 2) points on the spline used as boundary vertices.
    spacing : grid spacing, in the units of the polygon.
    lattice : put the grid on the lattice ``spacing · ℤ²`` (else it starts at the polygon's
        lower corner): a new outline then keeps the interior nodes where they were.
    grid : `lattice_grid` of ``polygon`` and ``spacing`` when its caller has it (``lattice``).
    Returns vertices (v, 2) float64 and faces (f, 3) int64, counter-clockwise.
    """
    if not np.isfinite(spacing) or spacing <= 0:
        raise FitError(f"grid spacing must be positive, got {spacing}")
    polygon = np.asarray(polygon, dtype=np.float64)
    if not np.array_equal(polygon[0], polygon[-1]):
        polygon = np.vstack([polygon, polygon[:1]])
    region = shapely.Polygon(polygon)
    shapely.prepare(region)
    # index: (ny+1, nx+1) vertex id of each grid node, -1 when unused; full: (ny, nx) cells.
    origin, index, grid_xy, full = grid or _grid_nodes(polygon, spacing, lattice)

    n_boundary = len(boundary_points)
    vertices = np.vstack([boundary_points, grid_xy])
    grid_faces = _full_cell_faces(full, index) + n_boundary

    # Band: boundary points + every used node that touches a non-full cell, plus one ring more so
    # that Delaunay sees the grid beyond the band's edge.
    touches_band = _nodes_touching(~full & _cells_with_any_node(index), dilate=1)
    band_nodes = index[touches_band & (index >= 0)]
    band_ids = np.concatenate([np.arange(n_boundary), band_nodes + n_boundary])
    band_faces = _delaunay_faces(vertices, band_ids)
    centroids = face_centres(vertices, band_faces)
    keep = shapely.contains_xy(region, centroids[:, 0], centroids[:, 1])
    keep &= ~_in_full_cell(centroids, origin, spacing, full)
    band_faces = band_faces[keep]
    faces = np.vstack([grid_faces, band_faces])

    border = _full_region_border(full, index) + n_boundary
    if not _stitched(band_faces, border, n_boundary, len(vertices)):
        all_ids = np.arange(len(vertices))
        faces = _delaunay_faces(vertices, all_ids)
        centroids = face_centres(vertices, faces)
        faces = faces[shapely.contains_xy(region, centroids[:, 0], centroids[:, 1])]
    if len(faces) == 0:
        raise FitError("no triangle lies inside the boundary spline")
    return _drop_unused(vertices, faces)


def lattice_grid(polygon: np.ndarray, spacing: float) -> tuple:
    """The grid `mesh_inside` (``lattice=True``) lays inside ``polygon`` (p, 2), for it and
    `lattice_nodes` to share (a re-mesh asks both, 1 ms each)."""
    polygon = np.asarray(polygon, dtype=np.float64)
    if not np.array_equal(polygon[0], polygon[-1]):
        polygon = np.vstack([polygon, polygon[:1]])
    return _grid_nodes(polygon, spacing, lattice=True)


def lattice_nodes(polygon: np.ndarray, spacing: float,
                  grid: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The lattice nodes `mesh_inside` (``lattice=True``) uses inside ``polygon`` (p, 2):
    ``first`` (2,) int64, the whole-number (x, y) of the corner node, and ``used``
    (rows, cols) bool, node (row j, column i) at ``(first + (i, j)) · spacing``. ``grid``:
    its `lattice_grid` when the caller has it."""
    lo, index, _, _ = grid or lattice_grid(polygon, spacing)
    return np.rint(lo / spacing).astype(np.int64), index >= 0


def _grid_nodes(polygon, spacing, lattice=False):
    lo = polygon.min(axis=0)
    first = np.floor(lo / spacing)  # on the lattice: the first node's whole-number coordinates
    if lattice:
        lo = first * spacing

    def node_xy(i, j):  # on the lattice, a node's coordinates do not depend on lo
        ij = np.column_stack([i, j]).astype(np.float64)
        return (first + ij) * spacing if lattice else lo + spacing * ij
    hi = polygon.max(axis=0)
    columns, rows = np.ceil((hi - lo) / spacing) + 2  # floats: a huge grid is no overflow
    if columns * rows > MAX_GRID_NODES:
        raise FitError(f"a grid spacing of {spacing:.3g} lays {columns * rows:.2g} nodes in the "
                       f"boundary's box (at most {MAX_GRID_NODES:.0e}): use a larger --spacing "
                       "or a smaller --extend")
    nx, ny = int(columns) - 1, int(rows) - 1
    inside = rasterize(polygon, lo, spacing, (ny + 1, nx + 1))
    # Nodes closer than half a spacing to the boundary would make slivers with the boundary points;
    # a node that close to a point of the dense ring is a corner of the point's cell (a cKDTree
    # of the ring and a query of the nodes round it took 0.45 ms of a 4.4 ms chart re-mesh).
    ring = _densify(polygon, spacing / 4)
    cells = np.floor((ring - lo) / spacing).astype(np.int64)
    corner_i = np.clip(cells[:, 0, None] + _CORNERS[:, 0], 0, nx)  # (r, 4)
    corner_j = np.clip(cells[:, 1, None] + _CORNERS[:, 1], 0, ny)
    xy = node_xy(corner_i.ravel(), corner_j.ravel()).reshape(-1, 4, 2)
    close = np.sqrt(np.sum((xy - ring[:, None, :]) ** 2, axis=2)) < 0.5 * spacing
    near = np.zeros_like(inside)
    near[corner_j[close], corner_i[close]] = True
    used = inside & ~near
    index = np.full(used.shape, -1, dtype=np.int64)
    index[used] = np.arange(int(used.sum()))
    full = used[:-1, :-1] & used[1:, :-1] & used[:-1, 1:] & used[1:, 1:]
    uj, ui = np.nonzero(used)
    return lo, index, node_xy(ui, uj), full


#: The (column, row) offsets of a cell's four corner nodes from its lower one.
_CORNERS = np.array([[0, 0], [1, 0], [0, 1], [1, 1]])


def rasterize(polygon, origin, spacing, shape):
    """(rows, cols) bool: which nodes ``origin + spacing · (col, row)`` of a grid lie inside the
    closed ``polygon`` (p, 2) (even-odd scanlines)."""
    rows, cols = shape
    p0, p1 = polygon[:-1], polygon[1:]
    ys = origin[1] + spacing * np.arange(rows)
    lo_y = np.minimum(p0[:, 1], p1[:, 1])
    hi_y = np.maximum(p0[:, 1], p1[:, 1])
    # Rows each edge crosses (half-open in y so a vertex on a scanline counts once).
    first = np.ceil((lo_y - origin[1]) / spacing).astype(np.int64)
    last = np.ceil((hi_y - origin[1]) / spacing).astype(np.int64) - 1
    counts = np.clip(last - first + 1, 0, None)
    edge = np.repeat(np.arange(len(p0)), counts)
    row = np.repeat(first, counts) + (
        np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    )
    ok = (row >= 0) & (row < rows)
    edge, row = edge[ok], row[ok]
    a, b = p0[edge], p1[edge]
    t = (ys[row] - a[:, 1]) / (b[:, 1] - a[:, 1])
    x = a[:, 0] + t * (b[:, 0] - a[:, 0])
    col = np.clip(np.ceil((x - origin[0]) / spacing).astype(np.int64), 0, cols)
    toggles = (np.bincount(row * (cols + 1) + col, minlength=rows * (cols + 1)) & 1).astype(bool)
    # the parity of the crossings left of each node (a 180 × 180 raster: 0.05 ms, 0.31 as the
    # remainder of an integer cumulative sum; a re-mesh rasterizes each chart's outline twice)
    return np.bitwise_xor.accumulate(toggles.reshape(rows, cols + 1), axis=1)[:, :cols]


def _full_cell_faces(full, index):
    j, i = np.nonzero(full)
    a, b = index[j, i], index[j, i + 1]
    c, d = index[j + 1, i + 1], index[j + 1, i]
    return np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])]).astype(np.int64)


def _cells_with_any_node(index):
    used = index >= 0
    return used[:-1, :-1] | used[1:, :-1] | used[:-1, 1:] | used[1:, 1:]


def _nodes_touching(cells, dilate=0):
    """(ny+1, nx+1) mask of grid nodes that are a corner of a marked cell, grown by ``dilate``."""
    nodes = np.zeros((cells.shape[0] + 1, cells.shape[1] + 1), dtype=bool)
    nodes[:-1, :-1] |= cells
    nodes[1:, :-1] |= cells
    nodes[:-1, 1:] |= cells
    nodes[1:, 1:] |= cells
    for _ in range(dilate):
        grown = nodes.copy()
        grown[1:, :] |= nodes[:-1, :]
        grown[:-1, :] |= nodes[1:, :]
        grown[:, 1:] |= nodes[:, :-1]
        grown[:, :-1] |= nodes[:, 1:]
        nodes = grown
    return nodes


def _in_full_cell(points, origin, spacing, full):
    cell = np.floor((points - origin) / spacing).astype(np.int64)
    i, j = cell[:, 0], cell[:, 1]
    valid = (i >= 0) & (j >= 0) & (i < full.shape[1]) & (j < full.shape[0])
    result = np.zeros(len(points), dtype=bool)
    result[valid] = full[j[valid], i[valid]]
    return result


#: Qhull's options for the band's Delaunay triangulation: joggled input ('QJ'), each simplex
#: found whole (the lattice's co-circular squares otherwise have their facets merged, then
#: triangulated again: 'Qt'), in half the time: 38 -> 18 ms for the 33 bands, 11,000 points, of
#: a figurine chart re-mesh, the same number of triangles and the same smallest. Deterministic.
_QHULL_OPTIONS = "QJ"


def _delaunay_faces(vertices, ids):
    if len(ids) < 3:
        return np.empty((0, 3), dtype=np.int64)
    simplices = Delaunay(vertices[ids], qhull_options=_QHULL_OPTIONS).simplices
    faces = ids[simplices]
    return _counter_clockwise(vertices, faces)


def _counter_clockwise(vertices, faces):
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    faces = faces.copy()
    flip = cross < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces


def _full_region_border(full, index):
    """(e, 2) grid-node ids of the edges on the border of the union of full cells."""
    padded = np.pad(full, 1)
    horizontal = padded[:-1, 1:-1] != padded[1:, 1:-1]  # (ny+1, nx): node (j,i)-(j,i+1)
    vertical = padded[1:-1, :-1] != padded[1:-1, 1:]  # (ny, nx+1): node (j,i)-(j+1,i)
    hj, hi = np.nonzero(horizontal)
    vj, vi = np.nonzero(vertical)
    return np.vstack(
        [
            np.column_stack([index[hj, hi], index[hj, hi + 1]]),
            np.column_stack([index[vj, vi], index[vj + 1, vi]]),
        ]
    )


def _stitched(band_faces, border_edges, n_boundary, n_vertices):
    """True when the band triangles share the full-cell region's border edges instead of
    overlapping it: no edge has more than two faces, and no open edge runs between grid nodes."""
    edges = np.vstack([half_edges(band_faces), border_edges])
    edges = np.sort(edges, axis=1)
    key = edges[:, 0] * n_vertices + edges[:, 1]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    if (counts > 2).any():
        return False
    open_edges = edges[counts[inverse] == 1]
    return bool((open_edges < n_boundary).any(axis=1).all())


def _drop_unused(vertices, faces):
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    used = np.flatnonzero(used)  # np.unique(faces), without its sort
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]


def _densify(polygon, step):
    seg = np.diff(polygon, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    counts = np.maximum(np.ceil(length / step).astype(int), 1)
    first = np.repeat(np.cumsum(counts) - counts, counts)
    t = (np.arange(counts.sum()) - first) / np.repeat(counts, counts)
    start = np.repeat(polygon[:-1], counts, axis=0)
    return start + np.repeat(seg, counts, axis=0) * t[:, None]


def signed_area(polygon: np.ndarray) -> float:
    """Shoelace area of a (p, 2) polygon, closed or not: > 0 counter-clockwise."""
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, next_rows(y)) - np.dot(y, next_rows(x)))


def next_rows(loop: np.ndarray) -> np.ndarray:
    """``np.roll(loop, -1, axis=0)``: row i holds row i + 1 of the closed ``loop``, the last
    the first (by slices: np.roll's overhead was a tenth of a chart's re-mesh)."""
    return np.concatenate([loop[1:], loop[:1]])


def previous_rows(loop: np.ndarray) -> np.ndarray:
    """``np.roll(loop, 1, axis=0)``: row i holds row i − 1 of the closed ``loop``."""
    return np.concatenate([loop[-1:], loop[:-1]])
