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
  two sheets touch are split (`mesh_edges.split_nonmanifold`): the mesh is the boundary of a volume,
  watertight. The grid is `reconstruct.closed_grid.ClosedSDF`'s, re-evaluated on a re-mesh
  only round the samples that changed.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import (
    breadth_first_order,
    minimum_spanning_tree,
)
from scipy.spatial import cKDTree

from .closed_grid import ClosedSDF
from .errors import InvalidInputError
from .grid_steps import exterior_of, farther_than, grid_box, occupancy
from .kdtree import QUERY_THREADS, PointTree
from .marching import marched
from .mesh_edges import (
    close_small_holes,
    edge_runs,
    face_centres,
    face_volumes,
    kept_faces,
    piece_labels,
    signed_volume,
    split_nonmanifold,
    topology,
    turn_faces,
)
from .sdf_grid import SparseSDF

#: The revision of the join's method, part of the key of the mesh a grid keeps (and saves): an
#: atlas saved by an earlier revision does not give its kept mesh back for the same samples (a
#: mug saved before the pocket votes changed kept its cut handle); its first re-mesh joins
#: afresh. Raise it when a change to the join changes its meshes.
JOIN_REVISION = 5
#: Steps, in median edges, at which a face across the border between two charts' parts is
#: filled with samples (`stretched_samples`). Hook scan (40 charts of an open join): at half an
#: edge the join had 19,600 samples instead of 11,000, and a new λ moved 8,600 of them instead of
#: 4,200 (join 349 -> 467 ms); at one edge 12,800 and 5,000, and the washers' holes all close.
ACROSS_STEP = 1.0


def chart_samples(meshes, labels, points, reach: float = np.inf, tree: PointTree | None = None,
                  charts=None):
    """Samples of each chart's surface inside its own part of the cloud.

    meshes : list of trimesh.Trimesh, one per chart; labels : (n,) chart of each input point
    (−1: none); points : (n, 3); reach : vertices farther than this from every input point are
    dropped (a chart's spline outline encloses the holes inside it; its mesh spans them);
    tree : a `kdtree.PointTree` of ``points[labels >= 0]`` if the caller keeps one (re-meshing
    does); charts : the label of each mesh's chart (default 0, 1, ...).
    Returns a list of (v_i,) vertex indices kept per chart."""
    tree = PointTree(points[labels >= 0]) if tree is None else tree
    return [np.flatnonzero(own) for own in owned([mesh.vertices for mesh in meshes], labels,
                                                 tree, reach, charts)]


def owned(positions, labels, tree: PointTree, reach: float = np.inf,
          charts=None, others: bool = False) -> list[np.ndarray]:
    """Which of each chart's ``positions`` (c arrays (v_i, 3)) lie in its own part of the cloud:
    their nearest input point is the chart's (``labels`` (n,), −1: none; ``charts`` (c,) the
    label of each array's chart, default 0, 1, ...; ``tree`` a `kdtree.PointTree` of the points
    with a label) and within ``reach``; with ``others``, in another chart's part instead.
    Returns c masks (v_i,)."""
    sizes = [len(p) for p in positions]
    # threads for the join's queries; a chart's few hundred nodes (`chart_parts.unchanged`)
    # took twice as long with them as without (starting them, 0.4 ms)
    distance, nearest = tree.query(np.concatenate(positions),
                                   workers=QUERY_THREADS if sum(sizes) > 5000 else 1)
    chart = np.repeat(np.arange(len(positions)) if charts is None else np.asarray(charts),
                      sizes)
    mine = labels[labels >= 0][nearest] == chart
    inside = (~mine if others else mine) & (distance <= reach)
    return np.split(inside, np.cumsum(sizes)[:-1])


def border_vertices(mesh: trimesh.Trimesh, kept: np.ndarray) -> np.ndarray:
    """(b,) the vertices of ``mesh`` not ``kept`` (k,) that share a face with one that is."""
    faces = np.asarray(mesh.faces)
    is_kept = np.zeros(len(mesh.vertices), bool)
    is_kept[kept] = True
    near = np.zeros(len(mesh.vertices), bool)
    near[faces[is_kept[faces].any(axis=1)].ravel()] = True
    return np.flatnonzero(near & ~is_kept)


def _stacked(meshes, kept):
    """The charts' ``meshes`` as one: vertex offsets (c + 1,), vertices (v, 3), faces (f, 3),
    and which vertices are ``kept`` (c arrays of indices into each mesh) as a mask (v,)."""
    offsets = np.cumsum([0, *(len(mesh.vertices) for mesh in meshes)])
    vertices = np.concatenate([mesh.vertices for mesh in meshes])
    faces = np.concatenate([np.asarray(mesh.faces) + offset
                            for mesh, offset in zip(meshes, offsets, strict=False)])
    mask = np.zeros(len(vertices), bool)
    mask[np.concatenate([k + offset for k, offset in zip(kept, offsets, strict=False)])] = True
    return offsets, vertices, faces, mask


def vertex_normals(meshes, kept) -> list[np.ndarray]:
    """The unit normals (k_i, 3) of the vertices ``kept`` (k_i,) of each of ``meshes``: trimesh's
    angle-weighted vertex normals, computed once for the faces round all the kept vertices
    (each mesh's ``vertex_normals`` took a third of a cached re-mesh's join)."""
    from trimesh.geometry import weighted_vertex_normals
    from trimesh.triangles import angles, normals

    offsets, vertices, faces, wanted = _stacked(meshes, kept)
    faces = faces[wanted[faces].any(axis=1)]
    triangles = vertices[faces]
    unit, valid = normals(triangles)
    face_normals = np.zeros((len(faces), 3))
    face_normals[valid] = unit
    summed = weighted_vertex_normals(len(vertices), faces, face_normals, angles(triangles))
    return [summed[k + offset] for k, offset in zip(kept, offsets, strict=False)]


def stretched_samples(meshes, kept, normals, stretch: float, across=None) -> list:
    """Samples on the charts' faces where their vertices alone leave gaps that an open join
    trims into slits and holes:
    - faces that their maps stretch: where a steep detail was compressed in the embedding, a
      chart's regular 2D grid lands in 3D with edges several times its others (relief 20k
      seed 1: 3-4.8 mm where the rest are 1-1.4);
    - faces across the border between two charts' parts: each chart's kept vertices stop
      short of it by up to an edge (a washer's two charts, 5k σ 0.5 %: holes 4-5 mm across on
      their border, capped only under 4).

    meshes : c chart meshes; kept : c arrays (k_i,) of the vertices the join keeps, with unit
    ``normals`` (k_i, 3); across : c arrays of the vertices in another chart's part (None:
    none). A face with every corner kept whose longest edge is over ``stretch`` times the
    median edge of its chart's such faces (``longest``) is filled at steps of ``longest``; a
    face with some corners kept and the others ``across``, at steps of `ACROSS_STEP` median
    edges at most (its edge between two kept corners as a full face's). Filled: its edges with a
    kept end get ceil(length / step) − 1 points along them, its inside the points of a
    barycentric lattice of ceil(longest side / step) steps, on the face (the chart's mesh: its
    network between the vertices strays from the surface where it stretches, figurine 20k:
    1.3 voxels off against 0.1 at the vertices), with normals interpolated from its kept
    corners'. The caller keeps those in the chart's part (`owned`). Returns c pairs of samples
    (q_i, 3) and unit normals (q_i, 3)."""
    offsets, vertices, faces, is_kept = _stacked(meshes, kept)
    is_across = np.zeros(len(vertices), bool)
    for where, offset in zip(across or (), offsets, strict=False):
        is_across[np.asarray(where, np.int64) + offset] = True
    chart = np.repeat(np.arange(len(meshes)), [len(mesh.faces) for mesh in meshes])
    corners = is_kept[faces]
    full = corners.all(axis=1)
    bordering = corners.any(axis=1) & ~full & (corners | is_across[faces]).all(axis=1)
    taken = full | bordering
    faces, chart, full, corners = faces[taken], chart[taken], full[taken], corners[taken]
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    squared = np.column_stack([np.einsum("ij,ij->i", d, d) for d in (a - b, b - c, c - a)])
    counts = np.bincount(chart[full], minlength=len(meshes))
    median = np.array([np.sqrt(np.median(part)) if len(part) else np.inf
                       for part in np.split(squared[full], np.cumsum(counts)[:-1])])[chart]
    longest = stretch * median
    step = np.where(full, longest, np.minimum(longest, ACROSS_STEP * median))  # (f,) insides
    # (f, 3) of the edges (corners 0-1, 1-2, 2-0): one between two kept corners as a full face's
    edge_step = np.where(corners & np.roll(corners, -1, axis=1), longest[:, None],
                         step[:, None])
    filled_faces = (squared > edge_step**2).any(axis=1) | (squared.max(axis=1) > (2 * step)**2)
    at = np.zeros((len(vertices), 3))  # a corner not kept weighs nothing in a sample's normal
    if len(kept):
        at[np.concatenate([np.asarray(k, np.int64) + offset
                           for k, offset in zip(kept, offsets, strict=False)])] = (
            np.concatenate([np.reshape(n, (-1, 3)) for n in normals]))
    # every chart's faces at once (one chart at a time: 0.4 ms each, a scan's 54 charts 22 ms):
    # its vertices' indices are its own, so are its edges, and its samples come in its order
    points, turned, source = _fill_faces(faces[filled_faces], np.sqrt(squared[filled_faces]),
                                         step[filled_faces], edge_step[filled_faces],
                                         vertices, at, is_kept)
    of_chart = np.searchsorted(offsets, source, side="right") - 1
    order = np.argsort(of_chart, kind="stable")
    ends = np.cumsum(np.bincount(of_chart, minlength=len(meshes)))[:-1]
    return list(zip(np.split(points[order], ends), np.split(turned[order], ends), strict=True))


def _fill_faces(faces, sides, step, edge_step, vertices, at, is_kept):
    """`stretched_samples` on ``faces`` (f, 3), each with a kept corner (``is_kept`` (v,)
    bool), their ``sides`` (f, 3) and the steps their insides (f,) and edges (f, 3) are filled
    at; ``at`` (v, 3) the kept vertices' normals (zero elsewhere). Returns the samples (q, 3),
    their unit normals (q, 3) and a vertex (q,) of the face or edge each lies on."""
    # the edges with a kept end, once each, at the finest step of their faces: points at
    # t = 1/m ... (m − 1)/m along them
    edges = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    # unique rows by one int64 key each (np.unique's rows, in the same order, four times as
    # fast)
    keys, inverse = np.unique(edges[:, 0] * np.int64(len(vertices)) + edges[:, 1],
                              return_inverse=True)
    edges = np.column_stack(np.divmod(keys, np.int64(len(vertices))))
    steps = np.zeros(len(edges), np.int64)
    np.maximum.at(steps, inverse.ravel(), np.ceil(sides / edge_step).astype(np.int64).ravel())
    wanted = (steps >= 2) & is_kept[edges].any(axis=1)
    edges, steps = edges[wanted], steps[wanted]
    along = np.repeat(steps, steps - 1)
    t = (np.arange(len(along)) - np.repeat(np.cumsum(steps - 1) - (steps - 1), steps - 1) + 1)
    t = (t / along)[:, None]
    a, b = np.repeat(edges, steps - 1, axis=0).T
    weights, members = [np.column_stack([1 - t, t])], [np.column_stack([a, b])]
    # and inside each face, the lattice points off its sides
    lattice = np.ceil(sides.max(axis=1) / step).astype(np.int64)
    for n in np.unique(lattice[lattice >= 3]).tolist():
        i, j = np.mgrid[1:n, 1:n].reshape(2, -1)
        inner = (n - i - j) >= 1
        w = np.column_stack([i[inner], j[inner], n - i[inner] - j[inner]]) / n  # (p, 3)
        which = faces[lattice == n]
        weights.append(np.tile(w, (len(which), 1)))
        members.append(np.repeat(which, len(w), axis=0))
    points = np.concatenate([np.einsum("pk,pkd->pd", w, vertices[m])
                             for w, m in zip(weights, members, strict=True)])
    turned = np.concatenate([np.einsum("pk,pkd->pd", w, at[m])
                             for w, m in zip(weights, members, strict=True)])
    turned /= np.maximum(np.linalg.norm(turned, axis=1, keepdims=True), 1e-300)
    return points, turned, np.concatenate([m[:, 0] for m in members])


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


def exterior_grid(samples, voxel: float, band: float = 3.0, normals=None, pad=None,
                  extra=None):
    """Which nodes of a grid round ``samples`` (m, 3) lie outside the sampled surface.

    A node farther than ``band`` voxels from every sample is *free*; the free nodes connected
    to the grid's border are exterior, and so is a pocket the samples' tangent planes, oriented
    by ``normals`` (m, 3), mostly put in front (`reconstruct.grid_steps.exterior_of`).
    ``extra`` (p, 3): points that occupy the grid like samples (data no chart represents),
    outside the grid ignored. Returns origin (3,), shape (3,), exterior and free, bool arrays
    of ``shape``."""
    samples = np.asarray(samples, float)
    origin, shape = grid_box(samples, voxel, band + 3 if pad is None else pad)
    occupied = occupancy(samples, extra, origin, shape, voxel)
    free = farther_than(occupied, band)
    return origin, shape, exterior_of(free, origin, voxel, samples, normals), free


class ExteriorProbe:
    """Which side of oriented samples is outside the object: `exterior_grid` of ``samples``
    (m, 3), looked up ``band + 1.5`` voxels along each normal and against it.

    ``extra`` (p, 3): data no chart represents (`reconstruct.chart_sides.uncharted_points`);
    free space that it encloses, occupying the grid as it does a closed join's, is not
    outside: a hole in the samples where the sheet graph left a junction's data out is not a
    hole in the surface (bench.atlas sheets 20k: through such holes by the plates' roots
    the inside of the foot was outside, its charts two-sided and joined as shells whose
    inner faces voted that inside outside again in the join; a hollow foot). Only what it
    encloses: the nodes it alone keeps from free keep their side (the noisy data either side
    of a curled ear charted once leaves the ear two-sided)."""

    def __init__(self, samples, voxel: float, band: float = 3.0, extra=None):
        self.origin, self.shape, self.exterior, _ = exterior_grid(samples, voxel, band)
        if extra is not None and len(extra):
            _, _, plugged, free = exterior_grid(samples, voxel, band, extra=extra)
            self.exterior &= ~(free & ~plugged)
        self.voxel, self.step = voxel, (band + 1.5) * voxel

    @classmethod
    def restored(cls, origin, exterior, voxel: float, step: float) -> ExteriorProbe:
        """The probe whose grid (``origin`` (3,), ``exterior`` (shape) bool), ``voxel`` and
        ``step`` were saved (an atlas's state: a loaded atlas turns its samples as the atlas
        saved did, not by a probe of the samples it was saved with)."""
        origin, exterior = np.asarray(origin, float), np.asarray(exterior)
        if origin.shape != (3,) or exterior.ndim != 3 or exterior.dtype != bool:
            raise ValueError(f"its exterior probe is not a grid (origin {origin.shape}, "
                             f"exterior {exterior.shape} {exterior.dtype})")
        probe = cls.__new__(cls)
        probe.origin, probe.exterior = origin, exterior
        probe.shape = np.asarray(probe.exterior.shape)
        probe.voxel, probe.step = float(voxel), float(step)
        return probe

    def sides(self, samples, normals) -> tuple[np.ndarray, np.ndarray]:
        """(m,) bool each: whether the probe in front of each of ``samples`` (m, 3) along its
        ``normals`` (m, 3) is outside, and whether the one behind it is."""
        def outside(p):
            index = np.floor((p - self.origin) / self.voxel + 0.5).astype(int)
            return self.exterior[tuple(np.clip(index, 0, self.shape - 1).T)]
        return outside(samples + self.step * normals), outside(samples - self.step * normals)

    def facing_in(self, samples, normals) -> np.ndarray:
        """(m,) bool: the samples whose probes clearly put the outside behind them (the one in
        front not outside, the one behind outside): in a closed cloud whose charts face out,
        the flap of a chart folded over an edge (hook 20k seed 4: the foot's side chart ran
        down inside the foot 2-3 mm from its corner and back out along its bottom with its
        normals into the foot, and the planes in front of it opened an air channel to the
        outside: Euler 0 against 2)."""
        front, back = self.sides(samples, normals)
        return back & ~front


def exterior_votes(chart_samples_, chart_normals, voxel: float, band: float = 3.0,
                   extra=None, probe: ExteriorProbe | None = None):
    """Which side of each chart is outside the object.

    chart_samples_, chart_normals : c arrays (m_i, 3), looked up in the `ExteriorProbe` of all
    samples (with ``extra``; ``probe`` if the caller built it).
    Returns votes (c,) in [−1, 1], the charts' mean of +1 when only the front probe is
    outside (the normal points out), −1 when only the back one is, 0 otherwise; and
    two_sided (c,), the share of samples with both probes outside (a sheet seen from both
    sides: an open surface, or a part thinner than the noise charted once)."""
    if probe is None:
        everything = np.concatenate([s for s in chart_samples_ if len(s)])
        probe = ExteriorProbe(everything, voxel, band, extra)
    votes, two_sided = np.zeros(len(chart_samples_)), np.zeros(len(chart_samples_))
    for index, (s, n) in enumerate(zip(chart_samples_, chart_normals, strict=True)):
        if len(s):
            front, back = probe.sides(s, n)
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
                  uncharted=None, grid: SparseSDF | ClosedSDF | None = None,
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
    passes by them (or a callable of the samples' cKDTree and of the samples added and removed
    since its last call, None when the grid is built afresh, giving them);
    grid : a `SparseSDF` (open) or `reconstruct.closed_grid.ClosedSDF` (closed) kept between
    calls: the grid is re-evaluated only round the samples that changed since, and the same
    samples give back the same mesh at once (then its ``hit_`` is True); one of the other kind
    is ignored;
    kept_open : (m,) bool, in a closed join: samples whose front (the nodes straight in front
    of them, `reconstruct.closed_grid._FRONT`) the grey opening may not fill: both faces of
    the shells of thin parts facing data left out of the charts (`reconstruct.atlas`; the far
    face matters: the void in front of it is a gap between sheets a few voxels wide, not a
    crack to seal; the near face faces the outside anyway)."""
    samples = np.asarray(samples, float)
    normals = np.asarray(normals, float)
    kind = ClosedSDF if closed else SparseSDF
    sdf = grid if isinstance(grid, kind) else kind(voxel, band)
    sdf.voxel, sdf.band = voxel, band
    if closed:
        sdf.seal = seal
        sdf.follow(samples, normals, kept_open, uncharted)
    else:
        sdf.follow(samples, normals)
    key = _mesh_key(trim, min_share, hole, closed, seal)
    kept = (kept_mesh(sdf, trim, min_share, hole, closed, seal)
            if data is None and sdf.n_changed_ == 0 else None)
    sdf.hit_ = kept is not None
    if sdf.hit_:
        return kept  # the same samples: the same mesh
    for name in ("mesh_", "mesh_key_", "topology_"):  # of other samples: kept no longer
        vars(sdf).pop(name, None)
    if closed:
        if not hasattr(sdf, "values_"):  # loaded without its grid, and its mesh not kept
            sdf.fit(samples, normals, kept_open, uncharted)
        vertices, faces = sdf.march()  # marched again only round what changed
    else:
        vertices, faces = marched(sdf.values_, voxel, sdf.mask_)
    values, origin = sdf.values_, sdf.origin_
    # one vertex per grid edge the surface crosses: two coincide (trimesh's process merges them)
    # only at a node whose value is zero to rounding (skipping it: 12 ms of a 45k-vertex join),
    # which a closed grid has none of (kept off the level: `closed_grid._OFF_LEVEL`)
    coincide = not closed and bool(np.abs(values).min(initial=np.inf) <= 1e-6 * voxel)
    mesh = trimesh.Trimesh(vertices + origin, faces, process=coincide)
    if len(mesh.faces) == 0:
        return mesh
    if not closed:
        centres = face_centres(mesh.vertices, mesh.faces)
        if data is None:
            far = sdf.farther_than(centres, trim * voxel)
        else:
            far = cKDTree(np.asarray(data, float)).query(
                centres, distance_upper_bound=trim * voxel * (1 + 1e-9),
                workers=QUERY_THREADS)[0] > trim * voxel
        mesh, _ = kept_faces(mesh, ~far)
        if len(mesh.faces) == 0:  # every face far from the data
            return mesh
    runs = edge_runs(np.asarray(mesh.faces))
    piece = piece_labels(mesh.faces, runs)
    volumes = face_volumes(mesh) if closed else None  # (a closed join's faces are all kept
    if piece.max() > 0:  # but in pieces dropped whole, and split_nonmanifold moves none)
        sizes = np.bincount(piece)
        largest = int(np.argmax(sizes))
        kept = sizes >= min_share * sizes[largest]
        if closed:  # a closed piece facing the other way: a void, which no scan sees
            kept &= ~_voids(piece, runs, largest, volumes)
            volumes = volumes[kept[piece]]
        mesh, runs = kept_faces(mesh, kept[piece], runs)
    if closed:
        parted = split_nonmanifold(mesh, runs)
        mesh, runs = parted, (runs if parted is mesh else None)
    else:
        capped = close_small_holes(mesh, max_length=hole * voxel, runs=runs)
        mesh, runs = capped, (runs if capped is mesh else None)
    facts = topology(np.asarray(mesh.faces), runs)
    if facts[0] and (signed_volume(mesh) if volumes is None else volumes.sum()) < 0:
        turn_faces(mesh)  # watertight, and turned in
    if sdf is grid and data is None:
        sdf.mesh_, sdf.mesh_key_, sdf.topology_ = _copied(mesh), key, facts
    return mesh


def _copied(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy of ``mesh``'s vertices and faces (``copy(include_cache=True)`` hashed both to
    check its cache: 5 ms of a 45k-vertex re-mesh)."""
    return trimesh.Trimesh(np.array(mesh.vertices), np.array(mesh.faces), process=False)


def _mesh_key(trim, min_share, hole, closed, seal) -> tuple:
    """What a mesh `implicit_mesh` keeps in its grid was made with, besides the samples."""
    return JOIN_REVISION, trim, min_share, hole, closed, seal


def kept_mesh(grid, trim: float = 1.5, min_share: float = 0.005, hole: float = 12.0,
              closed: bool = False, seal: float | None = None) -> trimesh.Trimesh | None:
    """A copy of the mesh `implicit_mesh` with these parameters last made through ``grid``
    (a loaded one's too) for the grid's samples as they are, or None if it keeps none."""
    if (not hasattr(grid, "mesh_")
            or getattr(grid, "mesh_key_", None) != _mesh_key(trim, min_share, hole, closed, seal)):
        return None
    return _copied(grid.mesh_)


def kept_topology(grid, faces) -> tuple[bool, bool, int] | None:
    """`mesh_edges.topology` of ``faces`` (f, 3) if they are those of the mesh ``grid`` keeps
    (`kept_mesh`), or those turned over (an open atlas turns its mesh to the side its cloud
    was seen from: the relief's re-mesh found its topology again, 7 ms), and it knows it;
    else None."""
    known = getattr(grid, "topology_", None)
    if known is None:
        return None
    kept, faces = np.asarray(grid.mesh_.faces), np.asarray(faces)
    if not (np.array_equal(kept, faces) or np.array_equal(kept[:, ::-1], faces)):
        return None
    return known


def _voids(piece: np.ndarray, runs, largest: int, volumes: np.ndarray) -> np.ndarray:
    """(p,) bool: which pieces of a closed join's mesh (``piece`` (f,) label of each face;
    ``runs`` its `edge_runs`; ``volumes`` its `face_volumes`) are voids: closed, and turned
    the other way from the ``largest`` (marching cubes orients every piece by the grid's sign,
    so such a piece bounds outside values enclosed by inside ones, within some solid piece).
    Two layers of samples under the surface, a thin part's shell meeting the charts beside it,
    close one (figurine 20k: a 600-face bubble 2 mm under an ear, Euler 4 instead of 2)."""
    _, order, run_start, run_length = runs
    open_edges = np.repeat(run_length != 2, run_length)  # the half-edges, in edge order
    n = int(piece.max()) + 1
    closed = np.bincount(piece[order[open_edges] // 3], minlength=n) == 0
    volume = np.bincount(piece, volumes, minlength=n)
    return closed & closed[largest] & (volume * volume[largest] < 0)


def faces_seen_side(vertices, faces, points, up=(0.0, 0.0, 1.0)) -> bool:
    """Whether the faces (f, 3) over ``vertices`` (v, 3) face the side their cloud ``points``
    (n, 3) was seen from, as a scan station or a scanner over a table sees a surface: from
    above and around (an open join's faces follow its charts' normals, and a network's map
    its embedding's handedness: an open cloud leaves both sides free; a relief at 6,000
    points faced down at 4 of 6 seeds). The faces vote, by area, for facing away from a
    point the cloud's diagonal below its centroid along ``up`` (3,): a relief faces up, the
    walls of a scanned object out (the part of a surface that faces up exceeds the part that
    faces down by what no one saw from below)."""
    up = check_up(up)
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0))) if len(points) else 0.0
    below = points.mean(axis=0) - max(diagonal, 1e-12) * up
    a, b, c = (np.asarray(vertices)[np.asarray(faces)[:, k]] for k in range(3))
    doubled_area_normal = np.cross(b - a, c - a)
    away = (a + b + c) / 3 - below
    away /= np.maximum(np.linalg.norm(away, axis=1), 1e-300)[:, None]
    return bool(np.einsum("ij,ij->", doubled_area_normal, away) >= 0)


def check_up(up) -> np.ndarray:
    """``up`` as a unit (3,) vector; `InvalidInputError` naming it if it is not a finite,
    non-zero 3-vector."""
    try:
        vector = np.asarray(up, float).reshape(3)
    except (TypeError, ValueError):
        raise InvalidInputError(f"up must be a 3-vector, got {up!r}") from None
    norm = float(np.linalg.norm(vector))
    if not (np.isfinite(norm) and norm > 0):
        raise InvalidInputError(f"up must be a finite, non-zero 3-vector, got {up!r}")
    return vector / norm
