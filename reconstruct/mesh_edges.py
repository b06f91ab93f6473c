"""A triangle mesh's edges, sorted once for every count of them: its topology (watertight,
winding, Euler characteristic), its pieces, its border loops and their caps, the vertices
where faces meet in more than one fan, split; and the faces' winding turned (trimesh's
``split``, ``fill_holes`` and ``invert`` did these for the join, slower or, for ``invert``,
with stale normals).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


def turn_faces(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Reverse the winding of every face of ``mesh`` (in place). trimesh's ``invert`` keeps
    face normals cached before it un-negated (trimesh 5.2: it sets the negated normals while
    the faces are still the old ones, its setter refuses them, and the old stay cached)."""
    mesh.faces = np.ascontiguousarray(np.asarray(mesh.faces)[:, ::-1])
    return mesh


def signed_volume(mesh: trimesh.Trimesh) -> float:
    """The volume a closed ``mesh`` encloses, negative when its faces turn inwards (trimesh's
    ``volume`` computes every mass property for it: 40 ms of a 45k-vertex re-mesh)."""
    return float(face_volumes(mesh).sum()) / 6.0


def face_volumes(mesh: trimesh.Trimesh) -> np.ndarray:
    """(f,) six times the signed volume of the tetrahedron of each face and the origin."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    # by coordinates, gathered from columns (rows and np.cross: 7 ms of 116k faces, this 3)
    (ax, bx, cx), (ay, by, cy), (az, bz, cz) = (
        np.ascontiguousarray(vertices[:, axis])[faces.T] for axis in range(3))
    return ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)


def face_centres(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(f, d) the centre of each of ``faces`` (f, 3) over ``vertices`` (v, d):
    ``vertices[faces].mean(axis=1)`` (trimesh's ``triangles_center``) to the bit, gathered
    from columns (the (f, 3, d) triangles and mean: 7 ms of 54k faces, this 0.5)."""
    columns = np.ascontiguousarray(np.asarray(vertices).T)
    corners = np.ascontiguousarray(np.asarray(faces).T)
    total = columns.take(corners[0], axis=1)
    total += columns.take(corners[1], axis=1)
    total += columns.take(corners[2], axis=1)
    return (total / 3).T


def split_nonmanifold(mesh: trimesh.Trimesh, runs=None) -> trimesh.Trimesh:
    """``mesh`` with every vertex where faces meet in more than one fan (or only along an edge
    shared by more than two faces) split into one vertex per fan: where marching cubes lets two
    sheets touch in a grid cell, they are parted. Positions are unchanged. ``runs``: the
    mesh's `edge_runs` if the caller has them."""
    faces = np.asarray(mesh.faces)
    n_faces = len(faces)
    directed, order, run_start, run_length = edge_runs(faces) if runs is None else runs
    if _one_fan_each(faces, directed, order, run_start, run_length):
        return mesh
    corner_a = (3 * np.arange(n_faces)[:, None] + np.array([0, 1, 2])).ravel()
    corner_b = (3 * np.arange(n_faces)[:, None] + np.array([1, 2, 0])).ravel()
    pairs = run_start[run_length == 2]
    first, second = order[pairs], order[pairs + 1]  # the two half-edges of each manifold edge
    # half-edge a→b of one face meets b→a of the other: join the corners at a and at b
    rows = np.concatenate([corner_a[first], corner_b[first]])
    cols = np.concatenate([corner_b[second], corner_a[second]])
    same = directed[first, 0] == directed[second, 0]  # faces wound against each other
    flipped = np.r_[same, same]
    cols[flipped] = np.concatenate([corner_a[second], corner_b[second]])[flipped]
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n_faces,) * 2)
    n_fans, fan = connected_components(graph, directed=False)
    if n_fans == len(mesh.vertices):  # one fan a vertex: nothing to split
        return mesh
    old_vertex = faces.ravel()
    order = np.argsort(fan, kind="stable")  # each fan's first corner (np.unique's index)
    first_corner = order[np.r_[True, fan[order][1:] != fan[order][:-1]]]
    return trimesh.Trimesh(np.asarray(mesh.vertices)[old_vertex[first_corner]],
                           fan.reshape(-1, 3), process=False)


def _one_fan_each(faces, directed, order, run_start, run_length) -> bool:
    """Whether every vertex of ``faces`` (f, 3; its `edge_runs`) has its faces in one fan,
    known cheaply when every edge has two faces wound against each other: then the faces
    round a vertex, stepped across the edges, form cycles, and the vertex has one fan when
    the cycle through one of its corners holds all of them (a 45k-vertex join: 6 ms instead
    of 17 ms for the corners' connected components). False when not known."""
    if len(faces) == 0 or not np.all(run_length == 2):
        return False
    first, second = order[run_start], order[run_start + 1]
    tails = directed[:, 0]
    if np.any(tails[first] == tails[second]):  # wound the same way: not known
        return False
    twin = np.empty(len(directed), np.int64)
    twin[first], twin[second] = second, first
    # half-edge h = a→b leaves a at the corner 3·face(h) + h % 3; its twin b→a enters a at the
    # twin's next corner: the corner at a of the face across the edge, twin + 1 but for the
    # third corner's, twin − 2 (as 3·(twin // 3) + (twin % 3 + 1) % 3, but numpy's % of int64
    # is slow: this check of a 59k-vertex join 10.4 -> 9.0 ms)
    following = twin + 1  # (3f,) next corner round its vertex
    following -= 3 * (following - 3 * (following // 3) == 0)
    corners = np.bincount(faces.ravel())
    used = np.flatnonzero(corners)
    start = np.empty(len(corners), np.int64)
    start[faces.ravel()] = np.arange(3 * len(faces))  # a corner of each vertex
    start = start[used]
    # one fan: the walk from its corner first comes back after as many steps as it has corners
    count, here = corners[used], start
    one_fan = np.ones(len(used), bool)
    for step in range(1, int(count.max()) + 1):
        here = following[here]
        back = here == start
        one_fan &= np.where(count == step, back, ~back | (count < step))
    return bool(one_fan.all())


def half_edges(faces: np.ndarray) -> np.ndarray:
    """(3f, 2) the half-edges of ``faces`` (f, 3), in the faces' direction (``take``: a list
    index along the rows' axis took 4.3 ms for 116k faces, this 0.5)."""
    return np.asarray(faces).take([0, 1, 1, 2, 2, 0], axis=1).reshape(-1, 2)


def _edge_keys(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The half-edges (3f, 2) of ``faces`` (f, 3), in the faces' direction, and one int64 key
    (3f,) per undirected edge (equal keys: the same edge; sorted keys: lexicographic order)."""
    directed = half_edges(faces)
    low = np.minimum(directed[:, 0], directed[:, 1]).astype(np.int64)
    high = np.maximum(directed[:, 0], directed[:, 1]).astype(np.int64)
    return directed, low * (int(high.max(initial=0)) + 1) + high


def edge_runs(faces: np.ndarray) -> tuple:
    """The edges of ``faces`` (f, 3) sorted once for every count of them: the half-edges
    (3f, 2) in the faces' direction, their indices (3f,) in the order of their undirected edges,
    and where each edge's run of half-edges starts in that order (e,) and how long it is (e,)."""
    directed, key = _edge_keys(faces)
    # stable: the faces of a march come in cell order, their keys in long sorted runs, which a
    # merge sort takes as they are (a 45k-vertex join: 4.5 ms against 14 for a quicksort);
    # which of an edge's half-edges comes first matters to no caller
    order = np.argsort(key, kind="stable")
    ordered = key[order]
    run_start = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]]) if len(key) else order
    return directed, order, run_start, np.diff(np.r_[run_start, len(key)])


def kept_faces(mesh: trimesh.Trimesh, keep: np.ndarray, runs=None) -> tuple:
    """``mesh`` with only the faces ``keep`` (f,) bool and the vertices they use (in order),
    and its `edge_runs` taken from ``runs``, the mesh's, if given (else None): as trimesh's
    ``update_faces`` and ``remove_unreferenced_vertices`` and a new `edge_runs`, which took
    13 and 8 ms of a 58k-vertex join. Returns (mesh, runs)."""
    faces = np.asarray(mesh.faces)
    new_face = np.cumsum(keep) - 1
    faces_kept = faces[keep]
    used = np.zeros(len(mesh.vertices), bool)
    used[faces_kept.ravel()] = True
    faces_kept = (np.cumsum(used) - 1)[faces_kept]
    kept = trimesh.Trimesh(np.asarray(mesh.vertices)[used], faces_kept, process=False)
    if runs is None:
        return kept, None
    # the vertices keep their order, so the edges do theirs, and each run its half-edges
    _, order, run_start, run_length = runs
    still = np.repeat(keep, 3)[order]
    old = order[still]
    run = np.repeat(np.arange(len(run_start)), run_length)[still]
    start = np.flatnonzero(np.r_[True, run[1:] != run[:-1]]) if len(run) else run
    directed = half_edges(faces_kept)
    face = old // 3  # (its remainder by subtraction: numpy's % of int64 is slow)
    return kept, (directed, 3 * new_face[face] + (old - 3 * face), start,
                  np.diff(np.r_[start, len(run)]))


def topology(faces: np.ndarray, runs=None) -> tuple[bool, bool, int]:
    """(watertight, winding consistent, Euler characteristic) of ``faces`` (f, 3), as trimesh's
    ``is_watertight``, ``is_winding_consistent`` and ``euler_number`` define them (every edge in
    exactly two faces; the two run opposite ways; referenced vertices − edges + faces), from one
    sort of the edges (trimesh's took 35 ms of a 45k-vertex re-mesh). ``runs``: `edge_runs`."""
    if len(faces) == 0:
        return False, False, 0
    directed, order, run_start, run_length = edge_runs(faces) if runs is None else runs
    pairs = run_start[run_length == 2]
    winding = bool(np.all(directed[order[pairs], 1] == directed[order[pairs + 1], 0]))
    referenced = int(np.count_nonzero(np.bincount(np.ravel(faces))))
    return bool(np.all(run_length == 2)), winding, referenced - len(run_start) + len(faces)


def piece_labels(faces: np.ndarray, runs=None) -> np.ndarray:
    """(f,) the piece of each of ``faces`` (f, 3), pieces joined across edges of exactly two
    faces (as trimesh's ``split`` finds them), from one integer key per edge (fast).
    ``runs``: `edge_runs` of the faces if the caller has them."""
    if len(faces) == 0:
        return np.zeros(0, np.int64)
    _, order, run_start, run_length = edge_runs(faces) if runs is None else runs
    pairs = run_start[run_length == 2]
    first, second = order[pairs] // 3, order[pairs + 1] // 3
    adjacency = coo_matrix((np.ones(len(first)), (first, second)), shape=(len(faces),) * 2)
    return connected_components(adjacency, directed=False)[1]


def border_loops(faces: np.ndarray, runs=None) -> list[np.ndarray]:
    """Closed loops (vertex indices, in the faces' direction) of the edges of ``faces`` (f, 3)
    that belong to one face only. A vertex where two loops touch is walked through once each.
    ``runs``: `edge_runs` of the faces if the caller has them."""
    return _walked_loops(_border_edges(faces, runs))


def _border_edges(faces: np.ndarray, runs=None) -> np.ndarray:
    """(b, 2) the edges of ``faces`` (f, 3) in one face only, in the faces' direction and
    order. ``runs``: `edge_runs` of the faces if the caller has them."""
    directed, order, run_start, run_length = edge_runs(faces) if runs is None else runs
    return directed[np.sort(order[run_start[run_length == 1]])]


def _walked_loops(border: np.ndarray) -> list[np.ndarray]:
    """The closed loops of the ``border`` edges (b, 2), each from its first edge's start."""
    following: dict[int, list[int]] = {}
    for a, b in border.tolist():
        following.setdefault(a, []).append(b)
    loops = []
    for start in list(following):
        while following.get(start):
            loop, here = [start], following[start].pop()
            while here != start and following.get(here):
                loop.append(here)
                here = following[here].pop()
            if here == start:
                loops += [np.array(cycle) for cycle in _simple_cycles(loop) if len(cycle) >= 3]
    return loops


def _simple_cycles(loop: list[int]) -> list[list[int]]:
    """Split a closed walk that passes a vertex more than once into simple cycles."""
    cycles, stack, at = [], [], {}
    for vertex in loop:
        if vertex in at:
            start = at[vertex]
            cycles.append(stack[start:])
            for dropped in stack[start + 1:]:
                at.pop(dropped)
            del stack[start + 1:]
        else:
            at[vertex] = len(stack)
            stack.append(vertex)
    cycles.append(stack)
    return cycles


def close_small_holes(mesh: trimesh.Trimesh, max_length: float, runs=None) -> trimesh.Trimesh:
    """Cap every border loop of ``mesh`` shorter than ``max_length``, wound like the faces
    beside it: a loop of 3 or 4 edges with 1 or 2 triangles (as trimesh's ``fill_holes``),
    a longer one with a fan about its centroid. Longer loops (borders, holes in the data)
    stay. ``runs``: the mesh's `edge_runs` if the caller has them. The mesh has no
    unreferenced or coincident vertices (marching cubes' mesh, as `implicit_mesh` passes it):
    they are neither merged nor dropped.

    The loops are the pieces of the border edges, measured at once; only the few where loops
    touch at a vertex are walked one by one (walking them all took 46 ms of a scan's 0.5 s
    open join)."""
    border = _border_edges(mesh.faces, runs)
    if len(border) == 0:
        return mesh
    vertices = np.asarray(mesh.vertices)
    ids, local = np.unique(border, return_inverse=True)
    local = local.reshape(-1, 2)
    n = len(ids)
    graph = coo_matrix((np.ones(len(local)), (local[:, 0], local[:, 1])), shape=(n, n))
    _, piece = connected_components(graph, directed=False)
    loop = piece[local[:, 0]]  # (b,) the piece of each edge
    touching = (np.bincount(local[:, 0], minlength=n) != 1) | (
        np.bincount(local[:, 1], minlength=n) != 1)
    simple = np.bincount(piece, touching) == 0  # every vertex starts and ends one edge
    size = np.bincount(loop, minlength=len(simple))
    length = np.bincount(loop, np.linalg.norm(vertices[border[:, 1]] - vertices[border[:, 0]],
                                              axis=1), minlength=len(simple))
    capped = simple & (size >= 3) & (length <= max_length)
    # a border edge a -> b lies in one face; a cap runs it b -> a
    following = np.full(n, -1)
    following[local[:, 0]] = local[:, 1]
    loops, first = np.unique(loop, return_index=True)  # each loop from its first edge
    loops, first = loops[capped[loops]], first[capped[loops]]
    l0, l1 = local[first, 0], local[first, 1]
    l2 = following[l1]
    l3 = following[l2]
    triangle, quad = size[loops] == 3, size[loops] == 4
    small = np.concatenate([np.column_stack([l2, l1, l0])[triangle],
                            np.column_stack([l3, l2, l1])[quad],
                            np.column_stack([l3, l1, l0])[quad]])
    fans = loops[size[loops] > 4]
    centre = np.full(len(simple), -1)
    centre[fans] = len(vertices) + np.arange(len(fans))
    fanned = centre[loop] >= 0
    faces = [np.asarray(mesh.faces), ids[small], np.column_stack(
        [ids[local[fanned, 1]], ids[local[fanned, 0]], centre[loop[fanned]]])]
    sums = [np.bincount(loop, vertices[border[:, 0], k], len(simple))[fans] for k in range(3)]
    new_vertices = [vertices, np.column_stack(sums) / size[fans, None]]
    count = len(vertices) + len(fans)
    for walked in _walked_loops(border[~simple[loop]]):  # loops touching at a vertex
        ring = vertices[walked]
        if np.linalg.norm(np.diff(ring, axis=0, append=ring[:1]), axis=1).sum() > max_length:
            continue
        if len(walked) == 3:
            faces.append(walked[None, ::-1])
        elif len(walked) == 4:
            faces.append(np.array([[walked[3], walked[2], walked[1]],
                                   [walked[3], walked[1], walked[0]]]))
        else:
            new_vertices.append(ring.mean(axis=0, keepdims=True))
            faces.append(np.column_stack([np.roll(walked, -1), walked,
                                          np.full(len(walked), count)]))
            count += 1
    added = np.concatenate(faces[1:])
    if len(added) == 0:
        return mesh
    # marching cubes gives one vertex per grid edge, and a centroid lands on none of them
    return trimesh.Trimesh(np.concatenate(new_vertices), np.concatenate([faces[0], added]),
                           process=False)
