"""Join the charts of an atlas into one mesh: orient them alike, then extract one surface
through their samples.

The charts' meshes overlap by their rings; trimmed to a partition of the cloud (`chart_samples`)
their vertices are samples of the fitted networks' surfaces, each with its mesh normal.
`orient_charts` makes the normals agree across charts: neighbouring charts compare their normals
at the points they share and a maximum spanning tree of that agreement propagates the flips
(Hoppe et al. 1992 propagate over points; here over charts, whose insides are already
consistent). Across a thin wall (a mug's inside and outside) charts share no points, so
`exterior_votes` also asks each chart which of its sides is outside: the grid nodes farther
than a band from every sample and connected to the grid's border (`exterior_grid`) are outside;
a probe along each normal and one against it are looked up there. A cloud whose charts mostly
answer clearly encloses a volume (closed); an open surface's charts are outside on both sides.

`implicit_mesh` evaluates an implicit moving-least-squares distance (Kolluri 2005: the
Gaussian-weighted mean of the signed distances to the nearest samples' tangent planes) near the
samples and extracts its zero level with scikit-image's marching cubes.
- Open: only within a band of the samples, faces farther than ``trim`` voxels from every sample
  dropped, so borders and holes wider than a few spacings stay open.
- Closed: the whole grid is signed. Beyond a voxel or two from the samples the value is the
  morphological closing of the samples (band voxels in from the exterior), so a gap between
  charts narrower than twice the band is capped near its data, never left open; straight in
  front of a sample (outside its tangent plane, within a voxel of its normal line) the planes
  hold instead (the closing is for the holes beside the samples, not for the space they face);
  the grid is opened and smoothed by a voxel (no sub-voxel tunnels; not in front of the
  ``kept_open`` samples, the shells of thin parts across a narrow gap), and vertices where
  two sheets touch are split (`split_nonmanifold`): the mesh is the boundary of a volume,
  watertight.
"""

from __future__ import annotations

import hashlib

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import (
    breadth_first_order,
    connected_components,
    minimum_spanning_tree,
)
from scipy.spatial import cKDTree

from .sdf_grid import SparseSDF, imls

#: Voxels from the nearest sample within which a closed join trusts the tangent planes alone.
_TRUSTED = 1.0
#: A closed join also trusts the planes at a node straight in front of its nearest sample (within
#: this many voxels of the sample's normal line, outside the planes): the closing, which fills
#: every void narrower than twice the seal, is meant for the holes beside the samples, not for
#: the space their normals face. bench.atlas 20k seed 0, Chamfer without / with (1 voxel): mug
#: 0.278 / 0.237, torus 0.123 / 0.103, figurine 0.165 / 0.153, hook 0.239 / 0.221, topology
#: unchanged; 0.5 voxel: mug 0.273, torus 0.117; 2 voxels: figurine Euler 4 (object 2).
_FRONT = 1.0
#: A closed join opens its signed grid (grey opening, a cube of this many voxels: thin voids
#: between two solids, sub-voxel tunnels, go) and smooths it (Gaussian, this many voxels)
#: before marching cubes. Cached 20k charts at σ 0.5 %, Euler with neither / with both:
#: figurine −28 / 2 (object 2; Chamfer 0.177 / 0.166, denoise 0.58 / 0.36), hook 2 / 2,
#: torus 0 / 0.
_OPEN = 3
_SMOOTH = 0.8
#: Threads of the KD-tree queries of `chart_samples` (a re-mesh's; the machine has 2 cores).
QUERY_THREADS = 2


def chart_samples(meshes, labels, points, reach: float = np.inf, tree: cKDTree | None = None):
    """Samples of each chart's surface inside its own part of the cloud.

    meshes : list of trimesh.Trimesh, one per chart; labels : (n,) chart of each input point
    (−1: none); points : (n, 3); reach : vertices farther than this from every input point are
    dropped (a chart's spline outline encloses the holes inside it; its mesh spans them);
    tree : a cKDTree of ``points[labels >= 0]`` if the caller keeps one (re-meshing does).
    Returns a list of (v_i,) vertex indices kept per chart."""
    charted = labels >= 0
    tree = cKDTree(points[charted]) if tree is None else tree
    sizes = [len(mesh.vertices) for mesh in meshes]
    distance, nearest = tree.query(np.concatenate([mesh.vertices for mesh in meshes]),
                                   workers=QUERY_THREADS)
    chart = np.repeat(np.arange(len(meshes)), sizes)
    inside = (labels[charted][nearest] == chart) & (distance <= reach)
    return [np.flatnonzero(part) for part in np.split(inside, np.cumsum(sizes)[:-1])]


def vertex_normals(meshes, kept) -> list[np.ndarray]:
    """The unit normals (k_i, 3) of the vertices ``kept`` (k_i,) of each of ``meshes``, computed
    for all at once: the faces' normals about a vertex weighted by their angles there
    (Thürrner & Wüthrich 1998, as trimesh's ``vertex_normals``, which took a third of a cached
    re-mesh's join one whole mesh at a time). Degenerate faces count for nothing."""
    sizes = [len(mesh.vertices) for mesh in meshes]
    offsets = np.cumsum([0, *sizes])
    vertices = np.concatenate([mesh.vertices for mesh in meshes])
    faces = np.concatenate([np.asarray(mesh.faces) + offset
                            for mesh, offset in zip(meshes, offsets, strict=False)])
    wanted = np.zeros(len(vertices), bool)
    wanted[np.concatenate([k + offset for k, offset in zip(kept, offsets, strict=False)])] = True
    faces = faces[wanted[faces].any(axis=1)]
    a, b, c = (vertices[faces[:, corner]] for corner in range(3))
    ab, ac, bc = b - a, c - a, c - b
    normals = np.cross(ab, ac)

    def length(vectors):
        return np.sqrt(np.einsum("ij,ij->i", vectors, vectors))

    with np.errstate(invalid="ignore", divide="ignore"):
        l_ab, l_ac, l_bc, area = length(ab), length(ac), length(bc), length(normals)
        first = np.arccos(np.clip(np.einsum("ij,ij->i", ab, ac) / (l_ab * l_ac), -1, 1))
        second = np.arccos(np.clip(-np.einsum("ij,ij->i", ab, bc) / (l_ab * l_bc), -1, 1))
        angles = np.column_stack([first, second, np.pi - first - second])
        normals /= area[:, None]
    # a degenerate face (an angle under trimesh's merge tolerance, or none) counts for nothing
    angles[~(angles >= 1e-8).all(axis=1) | ~(area > 0)] = 0.0
    normals[~(area > 0)] = 0.0
    weighted = (angles[:, :, None] * normals[:, None, :]).reshape(-1, 3)
    summed = np.column_stack([np.bincount(faces.ravel(), weighted[:, axis], len(vertices))
                              for axis in range(3)])
    norm = length(summed)
    summed[norm > 0] /= norm[norm > 0, None]
    return [summed[k + offset] for k, offset in zip(kept, offsets, strict=False)]


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


def _grid(samples: np.ndarray, voxel: float, pad: float):
    """Origin (3,) and shape (3,) of a grid of spacing ``voxel`` round ``samples`` (m, 3)."""
    origin = samples.min(axis=0) - pad * voxel
    shape = np.ceil((samples.max(axis=0) + pad * voxel - origin) / voxel).astype(int) + 1
    return origin, shape


def exterior_grid(samples, voxel: float, band: float = 3.0, normals=None, pad=None,
                  extra=None):
    """Which nodes of a grid round ``samples`` (m, 3) lie outside the sampled surface.

    A node farther than ``band`` voxels from every sample is *free*; the free nodes connected
    to the grid's border are exterior. A free pocket enclosed by the samples (the inside of a
    closed object, or a concave nook the band closed off) is exterior when the nearest
    samples' tangent planes, oriented by ``normals`` (m, 3), put most of its nodes in front
    (without normals: never). ``extra`` (p, 3): points that occupy the grid like samples
    (data no chart represents), outside the grid ignored. Returns origin (3,), shape (3,),
    exterior and free, bool arrays of ``shape``."""
    from scipy import ndimage

    samples = np.asarray(samples, float)
    origin, shape = _grid(samples, voxel, band + 3 if pad is None else pad)
    occupied = np.zeros(shape, bool)
    occupied[tuple(np.floor((samples - origin) / voxel + 0.5).astype(int).T)] = True
    if extra is not None and len(extra):
        nodes = np.floor((np.asarray(extra, float) - origin) / voxel + 0.5).astype(int)
        occupied[tuple(nodes[np.all((nodes >= 0) & (nodes < shape), axis=1)].T)] = True
    free = ndimage.distance_transform_edt(~occupied) > band
    pieces, _ = ndimage.label(free)
    faces = [pieces[0], pieces[-1], pieces[:, 0], pieces[:, -1], pieces[:, :, 0],
             pieces[:, :, -1]]
    outside = np.unique(np.concatenate([f.ravel() for f in faces]))
    outside = outside[outside > 0]
    if normals is not None and pieces.max() > 0:
        enclosed = free & ~np.isin(pieces, outside)
        if enclosed.any():
            nodes, label = _voters(np.argwhere(enclosed), pieces[enclosed])
            nearest = cKDTree(samples).query(origin + voxel * nodes)[1]
            front = np.einsum("gi,gi->g", origin + voxel * nodes - samples[nearest],
                              np.asarray(normals, float)[nearest]) > 0
            share = np.bincount(label, front, minlength=pieces.max() + 1) / np.maximum(
                np.bincount(label, minlength=pieces.max() + 1), 1)
            outside = np.union1d(outside, np.flatnonzero(share > 0.5))
    return origin, shape, np.isin(pieces, outside) & free, free


#: Nodes of one enclosed pocket that vote on its side (`exterior_grid`), evenly taken: its share
#: in front to about ±1 %. All of a torus's inside (181,604 nodes) took 0.8 s of a 1.9 s re-mesh.
_VOTERS = 4096


def _voters(nodes: np.ndarray, label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """At most `_VOTERS` of the ``nodes`` (g, 3) of each pocket ``label`` (g,), every k-th in
    grid order; returns (nodes, label) of those."""
    counts = np.bincount(label)
    order = np.argsort(label, kind="stable")
    first = np.cumsum(counts) - counts
    rank = np.arange(len(order)) - first[label[order]]
    step = -(-counts // _VOTERS)
    keep = order[rank % step[label[order]] == 0]
    keep.sort()
    return nodes[keep], label[keep]


def exterior_votes(chart_samples_, chart_normals, voxel: float, band: float = 3.0):
    """Which side of each chart is outside the object.

    chart_samples_, chart_normals : c arrays (m_i, 3). A probe ``band + 1.5`` voxels along
    each sample's normal and one against it are looked up in `exterior_grid` of all samples.
    Returns votes (c,) in [−1, 1], the charts' mean of +1 when only the front probe is
    outside (the normal points out), −1 when only the back one is, 0 otherwise; and
    two_sided (c,), the share of samples with both probes outside (a sheet seen from both
    sides: an open surface, or a part thinner than the noise charted once)."""
    everything = np.concatenate([s for s in chart_samples_ if len(s)])
    origin, shape, exterior, _ = exterior_grid(everything, voxel, band)
    step = (band + 1.5) * voxel

    def outside(p):
        index = np.clip(np.floor((p - origin) / voxel + 0.5).astype(int), 0, shape - 1)
        return exterior[tuple(index.T)]

    votes, two_sided = np.zeros(len(chart_samples_)), np.zeros(len(chart_samples_))
    for index, (s, n) in enumerate(zip(chart_samples_, chart_normals, strict=True)):
        if len(s):
            front, back = outside(s + step * n), outside(s - step * n)
            votes[index] = np.mean(front.astype(float) - back)
            two_sided[index] = np.mean(front & back)
    return votes, two_sided


def thin_shell(samples, normals, half: float):
    """A closed shell of thickness 2 ``half`` round a sheet sampled once (m, 3) with normals
    (m, 3): its samples moved ``half`` along and against their normals, facing away from the
    sheet. Returns samples (2m, 3) and normals (2m, 3)."""
    return (np.concatenate([samples + half * normals, samples - half * normals]),
            np.concatenate([normals, -normals]))


def implicit_mesh(samples, normals, voxel: float, band: float = 3.0, trim: float = 1.5,
                  min_share: float = 0.005, data=None, hole: float = 12.0,
                  closed: bool = False, seal: float | None = None,
                  uncharted=None, grid: SparseSDF | None = None,
                  kept_open=None) -> trimesh.Trimesh:
    """One mesh through oriented samples (m, 3) with unit normals (m, 3).

    voxel : grid spacing; band : the surface is sought within ``band`` voxels of a sample;
    trim : faces farther than ``trim`` voxels from every point of ``data`` (p, 3; default the
    samples) are dropped, so holes in the data stay open while gaps between the samples
    where data exists (a sharp edge no chart reached) are closed;
    min_share : pieces with fewer faces than this share of the largest are dropped;
    hole : border loops shorter than ``hole`` voxels are capped (`close_small_holes`): pinholes
    where no chart's samples reached, not holes in the data (12 voxels: under 4 across);
    closed : the samples enclose a volume (their normals point out of it). The whole grid is
    then signed: nodes beyond the band get the side `exterior_grid` finds, so a gap between
    the samples is closed across rather than left open, and nothing is trimmed: the surface
    is the boundary of a volume (watertight, manifold where marching cubes is);
    seal : the band (voxels) of `exterior_grid` in a closed join (default ``band``): gaps
    between the samples narrower than twice this are capped;
    uncharted : (p, 3) data points no chart's samples represent (a junction the charts left
    out): in a closed join they occupy the grid like samples, so the cap across their gap
    passes by them (or a callable giving them, called only when the mesh is built);
    grid : a `SparseSDF` kept between calls: the distance is re-evaluated only near the samples
    that changed since, and the same samples give back the same mesh at once (then its
    ``hit_`` is True);
    kept_open : (m,) bool, in a closed join: samples whose front (the nodes straight in front
    of them, `_FRONT`) the grey opening may not fill: both faces of the shells of thin parts
    facing data left out of the charts (`reconstruct.atlas`; the far face matters: the void in
    front of it is a gap between sheets a few voxels wide, not a crack to seal; the near face
    faces the outside anyway)."""
    from skimage.measure import marching_cubes  # scikit-image: only on the joining path

    samples = np.asarray(samples, float)
    normals = np.asarray(normals, float)
    sdf = SparseSDF(voxel, band) if grid is None else grid
    sdf.voxel, sdf.band = voxel, band
    sdf.follow(samples, normals)
    key = (trim, min_share, hole, closed, seal, None if kept_open is None
           else hashlib.sha1(np.packbits(np.asarray(kept_open, bool))).hexdigest())
    sdf.hit_ = bool(data is None and sdf.n_changed_ == 0
                    and getattr(sdf, "mesh_key_", None) == key)
    if sdf.hit_:
        return sdf.mesh_.copy(include_cache=True)  # the same samples: the same mesh
    tree = sdf.tree_
    if closed:
        from scipy import ndimage

        seal = band if seal is None else seal
        origin, shape, exterior, free = exterior_grid(samples, voxel, seal, normals,
                                                      extra=uncharted() if callable(uncharted)
                                                      else uncharted)
        axes = [origin[i] + voxel * np.arange(shape[i]) for i in range(3)]
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        near = ~free.ravel()
        # The closing of the samples by the seal (Serra 1982): seal voxels in from the exterior.
        # It caps a gap between the samples near their level instead of at the seal's edge.
        values = np.clip(seal * voxel - voxel * ndimage.distance_transform_edt(~exterior),
                         -(band + 1) * voxel, (band + 1) * voxel).ravel()
        planes, d, index = imls(nodes[near], samples, normals, tree, voxel, return_index=True)
        # the tangent planes within a voxel of a sample, the closing from two on, except straight
        # in front of the nearest sample (outside the planes), where the planes hold
        blend = np.clip(d[:, 0] / voxel - _TRUSTED, 0.0, 1.0)
        nearest = index[:, 0]
        ahead = np.einsum("gi,gi->g", nodes[near] - samples[nearest], normals[nearest])
        lateral = np.sqrt(np.maximum(d[:, 0] ** 2 - ahead**2, 0.0))
        front = (ahead > 0) & (lateral <= _FRONT * voxel) & (planes > 0)
        blend[front] = 0.0
        values[near] = (1 - blend) * planes + blend * values[near]
        values = values.reshape(shape)
        if _OPEN:
            opened = ndimage.grey_opening(values, size=(_OPEN,) * 3)
            if kept_open is not None:
                held = np.flatnonzero(near)[front & np.asarray(kept_open, bool)[nearest]]
                opened.flat[held] = np.maximum(opened.flat[held], values.flat[held])
            values = opened
        if _SMOOTH:
            values = ndimage.gaussian_filter(values, _SMOOTH)
        mask = None
    else:
        values, mask, origin = sdf.values_, sdf.mask_, sdf.origin_
    vertices, faces, _, _ = marching_cubes(values, level=0.0, spacing=(voxel,) * 3, mask=mask,
                                           gradient_direction="ascent", allow_degenerate=False)
    mesh = trimesh.Trimesh(vertices + origin, faces, process=True)
    if len(mesh.faces) == 0:
        return mesh
    if not closed:
        near_tree = tree if data is None else cKDTree(np.asarray(data, float))
        far = near_tree.query(mesh.triangles_center)[0] > trim * voxel
        mesh.update_faces(~far)
        mesh.remove_unreferenced_vertices()
    pieces = mesh.split(only_watertight=False) if n_pieces(mesh.faces) > 1 else [mesh]
    if len(pieces) > 1:
        largest = max(pieces, key=lambda p: len(p.faces))
        kept = [p for p in pieces if len(p.faces) >= min_share * len(largest.faces)]
        if closed:  # a closed piece facing the other way: a void, which no scan sees
            kept = [p for p in kept if not _void(p, largest)]
        mesh = trimesh.util.concatenate(kept)
    if closed:
        mesh = split_nonmanifold(mesh)
    else:
        mesh = close_small_holes(mesh, max_length=hole * voxel)
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()
    if grid is not None and data is None:
        sdf.mesh_, sdf.mesh_key_ = mesh.copy(include_cache=True), key
    return mesh


def _void(piece: trimesh.Trimesh, largest: trimesh.Trimesh) -> bool:
    """Whether ``piece`` of a closed join is a void: closed, and turned the other way from
    ``largest`` (marching cubes orients every piece by the grid's sign, so such a piece bounds
    outside values enclosed by inside ones, within some solid piece). Two layers of
    samples under the surface, a thin part's shell meeting the charts beside it, close one
    (figurine 20k: a 600-face bubble 2 mm under an ear, Euler 4 instead of 2)."""
    return (piece is not largest and piece.is_watertight and largest.is_watertight
            and piece.volume * largest.volume < 0)


def split_nonmanifold(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` with every vertex where faces meet in more than one fan (or only along an edge
    shared by more than two faces) split into one vertex per fan: where marching cubes lets two
    sheets touch in a grid cell, they are parted. Positions are unchanged."""
    faces = np.asarray(mesh.faces)
    n_faces = len(faces)
    directed, key = _edge_keys(faces)
    corner_a = (3 * np.arange(n_faces)[:, None] + np.array([0, 1, 2])).ravel()
    corner_b = (3 * np.arange(n_faces)[:, None] + np.array([1, 2, 0])).ravel()
    _, edge, counts = np.unique(key, return_inverse=True, return_counts=True)
    edge = edge.ravel()
    manifold = np.flatnonzero(counts[edge] == 2)
    order = manifold[np.argsort(edge[manifold], kind="stable")]
    first, second = order[0::2], order[1::2]  # the two half-edges of each manifold edge
    # half-edge a→b of one face meets b→a of the other: join the corners at a and at b
    rows = np.concatenate([corner_a[first], corner_b[first]])
    cols = np.concatenate([corner_b[second], corner_a[second]])
    same = directed[first, 0] == directed[second, 0]  # faces wound against each other
    flipped = np.r_[same, same]
    cols[flipped] = np.concatenate([corner_a[second], corner_b[second]])[flipped]
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n_faces,) * 2)
    _, fan = connected_components(graph, directed=False)
    old_vertex = faces.ravel()
    _, first_corner = np.unique(fan, return_index=True)
    if len(first_corner) == len(mesh.vertices):
        return mesh
    return trimesh.Trimesh(np.asarray(mesh.vertices)[old_vertex[first_corner]],
                           fan.reshape(-1, 3), process=False)


def _edge_keys(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The half-edges (3f, 2) of ``faces`` (f, 3), in the faces' direction, and one int64 key
    (3f,) per undirected edge (equal keys: the same edge; sorted keys: lexicographic order)."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    ordered = np.sort(directed, axis=1).astype(np.int64)
    return directed, ordered[:, 0] * (int(ordered.max(initial=0)) + 1) + ordered[:, 1]


def n_pieces(faces: np.ndarray) -> int:
    """Number of pieces of ``faces`` (f, 3) joined across edges of exactly two faces (as
    trimesh's ``split`` counts them), found from one integer key per edge (fast)."""
    if len(faces) == 0:
        return 0
    _, key = _edge_keys(faces)
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
    directed, key = _edge_keys(faces)
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
