"""Join the charts of an atlas into one mesh: orient them alike, then extract one surface
through their samples.

The charts' meshes overlap by their rings; trimmed to a partition of the cloud (`chart_samples`)
their vertices are samples of the fitted networks' surfaces, each with its mesh normal.
`orient_charts` makes the normals agree across charts: neighbouring charts compare their normals
at the points they share and a maximum spanning tree of that agreement propagates the flips
(Hoppe et al. 1992 propagate over points; here over charts, whose insides are already
consistent). `implicit_mesh` evaluates an implicit moving-least-squares distance (Kolluri 2005:
the Gaussian-weighted mean of the signed distances to the nearest samples' tangent planes) on a
voxel grid near the samples and extracts its zero level with scikit-image's marching cubes:
closed where the samples close, and faces farther than ``trim`` voxels from every sample
dropped, so borders and holes wider than a few spacings stay open.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from .sdf_grid import SparseSDF


def chart_samples(meshes, labels, points, reach: float = np.inf):
    """Samples of each chart's surface inside its own part of the cloud.

    meshes : list of trimesh.Trimesh, one per chart; labels : (n,) chart of each input point
    (−1: none); points : (n, 3); reach : vertices farther than this from every input point are
    dropped (a chart's spline outline encloses the holes inside it; its mesh spans them).
    Returns a list of (v_i,) vertex indices kept per chart."""
    charted = labels >= 0
    tree = cKDTree(points[charted])
    owner = labels[charted]
    kept = []
    for index, mesh in enumerate(meshes):
        distance, nearest = tree.query(mesh.vertices)
        kept.append(np.flatnonzero((owner[nearest] == index) & (distance <= reach)))
    return kept


def orient_charts(meshes, charts, points) -> np.ndarray:
    """Signs (c,) ±1 making the charts' normals agree where they overlap.

    meshes : c fitted chart meshes; charts : c index arrays into points (n, 3), the points each
    chart was fitted to (core and ring)."""
    n_charts = len(meshes)
    normal_at = np.zeros((n_charts, len(points), 3))
    for index, (mesh, members) in enumerate(zip(meshes, charts, strict=True)):
        nearest = cKDTree(mesh.vertices).query(points[members])[1]
        normal_at[index, members] = mesh.vertex_normals[nearest]
    rows, cols, agreement = [], [], []
    for a in range(n_charts):
        for b in range(a + 1, n_charts):
            shared = np.intersect1d(charts[a], charts[b], assume_unique=True)
            if len(shared) == 0:
                continue
            na, nb = normal_at[a, shared], normal_at[b, shared]
            rows.append(a)
            cols.append(b)
            agreement.append(float(np.einsum("ij,ij->", na, nb)))
    signs = np.ones(n_charts)
    if not rows:
        return signs
    agreement = np.array(agreement)
    # maximum spanning tree of |agreement| (minimum of its inverse)
    weight = 1.0 / (np.abs(agreement) + 1e-9)
    tree = minimum_spanning_tree(coo_matrix((weight, (rows, cols)), shape=(n_charts,) * 2))
    tree = tree + tree.T
    sign_of = {}
    for a, b, s in zip(rows, cols, np.sign(agreement), strict=True):
        sign_of[(a, b)] = sign_of[(b, a)] = s if s != 0 else 1.0
    done = np.zeros(n_charts, bool)
    for root in np.argsort([-len(c) for c in charts]):
        if done[root]:
            continue
        order, parent = breadth_first_order(tree, root, directed=False)
        for node in order[1:]:
            signs[node] = signs[parent[node]] * sign_of[(parent[node], node)]
        done[order] = True
    return signs


def implicit_mesh(samples, normals, voxel: float, band: float = 3.0, trim: float = 1.5,
                  min_share: float = 0.005, data=None, hole: float = 12.0,
                  grid: SparseSDF | None = None) -> trimesh.Trimesh:
    """One mesh through oriented samples (m, 3) with unit normals (m, 3).

    voxel : grid spacing; band : the surface is sought within ``band`` voxels of a sample;
    trim : faces farther than ``trim`` voxels from every point of ``data`` (p, 3; default the
    samples) are dropped, so holes in the data stay open while gaps between the samples
    where data exists (a sharp edge no chart reached) are closed;
    min_share : pieces with fewer faces than this share of the largest are dropped;
    hole : border loops shorter than ``hole`` voxels are capped (`close_small_holes`): pinholes
    where no chart's samples reached, not holes in the data (12 voxels: under 4 across);
    grid : a `SparseSDF` kept between calls: the distance is re-evaluated only near the samples
    that changed since, and the same samples give back the same mesh at once."""
    from skimage.measure import marching_cubes  # scikit-image: only on the joining path

    samples = np.asarray(samples, float)
    normals = np.asarray(normals, float)
    sdf = SparseSDF(voxel, band) if grid is None else grid
    sdf.voxel, sdf.band = voxel, band
    sdf.follow(samples, normals)
    key = (trim, min_share, hole)
    if data is None and sdf.n_changed_ == 0 and getattr(sdf, "mesh_key_", None) == key:
        return sdf.mesh_.copy(include_cache=True)  # the same samples: the same mesh
    values, mask, origin, tree = sdf.values_, sdf.mask_, sdf.origin_, sdf.tree_
    vertices, faces, _, _ = marching_cubes(values, level=0.0, spacing=(voxel,) * 3, mask=mask,
                                           gradient_direction="ascent", allow_degenerate=False)
    mesh = trimesh.Trimesh(vertices + origin, faces, process=True)
    if len(mesh.faces) == 0:
        return mesh
    near_tree = tree if data is None else cKDTree(np.asarray(data, float))
    far = near_tree.query(mesh.triangles_center)[0] > trim * voxel
    mesh.update_faces(~far)
    mesh.remove_unreferenced_vertices()
    pieces = mesh.split(only_watertight=False) if n_pieces(mesh.faces) > 1 else [mesh]
    if len(pieces) > 1:
        largest = max(len(p.faces) for p in pieces)
        mesh = trimesh.util.concatenate([p for p in pieces if len(p.faces) >= min_share * largest])
    mesh = close_small_holes(mesh, max_length=hole * voxel)
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()
    if grid is not None and data is None:
        sdf.mesh_, sdf.mesh_key_ = mesh.copy(include_cache=True), key
    return mesh


def n_pieces(faces: np.ndarray) -> int:
    """Number of pieces of ``faces`` (f, 3) joined across edges of exactly two faces (as
    trimesh's ``split`` counts them), found from one integer key per edge (fast)."""
    if len(faces) == 0:
        return 0
    ordered = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1).astype(np.int64)
    key = ordered[:, 0] * (int(ordered.max()) + 1) + ordered[:, 1]
    order = np.argsort(key, kind="stable")
    run_start = np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1]])
    run_length = np.diff(np.r_[run_start, len(key)])
    pairs = run_start[run_length == 2]
    first, second = order[pairs] // 3, order[pairs + 1] // 3
    adjacency = coo_matrix((np.ones(len(first)), (first, second)), shape=(len(faces),) * 2)
    return int(connected_components(adjacency, directed=False)[0])


def border_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed loops (vertex indices, in the faces' direction) of the edges of ``faces`` (f, 3)
    that belong to one face only. A vertex where two loops touch is walked through once each."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    ordered = np.sort(directed, axis=1).astype(np.int64)
    key = ordered[:, 0] * (int(ordered.max(initial=0)) + 1) + ordered[:, 1]  # one int per edge
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    border = directed[counts[inverse.ravel()] == 1]
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


def close_small_holes(mesh: trimesh.Trimesh, max_length: float) -> trimesh.Trimesh:
    """Cap every border loop of ``mesh`` shorter than ``max_length`` with a fan about its
    centroid, wound like the faces beside it. Longer loops (borders, holes in the data) stay."""
    loops = border_loops(mesh.faces)
    vertices, faces = [mesh.vertices], [mesh.faces]
    count = len(mesh.vertices)
    for loop in loops:
        ring = mesh.vertices[loop]
        if np.linalg.norm(np.diff(ring, axis=0, append=ring[:1]), axis=1).sum() > max_length:
            continue
        vertices.append(ring.mean(axis=0, keepdims=True))
        # a border edge a → b lies in one face; the cap runs it b → a
        faces.append(np.column_stack([np.roll(loop, -1), loop, np.full(len(loop), count)]))
        count += 1
    if count == len(mesh.vertices):
        return mesh
    return trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=True)
