"""Which side of each chart of an atlas is outside the object, whether the cloud is closed, and
which charts are the one face of a part thinner than the noise.

`exterior_votes` (reconstruct.join) asks each chart which of its sides is outside: a closed
cloud's charts say so clearly (mug, torus, hook, figurine 20k: 81–100 % of the samples); an open
one's, seen from both sides, do not (relief: none). A hole in the samples wider than twice the
band lets the outside in and every chart looks two-sided: a seal of twice the band is tried too,
and taken when the charts it leaves two-sided hold few of the samples (`WIDER_SEAL_TWO_SIDED`),
else the cloud is joined open. Where the data lies in such a hole (points the sheet graph left
out, at a junction) the votes count it as the join does: what it encloses is not outside
(`uncharted_points`, bench.atlas sheets 20k seeds 0 / 1: the foot's charts were two-sided
through holes by the plates' roots, joined as shells, the foot hollow; Chamfer 0.454 / 0.438 ->
0.416 / 0.429, Euler -30 / -16 -> -8 / 0, the gap's mid-plane outside 98.6 / 99.4 % -> 98.9 /
99.4 %).

Two plates a few noise widths apart (sheets: 1.5 mm plates 3 mm apart at σ 0.75 mm) look like
one slab to the votes: the gap is narrower than twice the band, each plate is charted on its
outer face (the sheet graph leaves the points of the faces towards the gap out) and both charts
face out. The data behind such a chart, uncharted, tells it apart from a slab's face (the mug's
4 mm wall: no data inside): it is *thin*, joined as a shell whose far face keeps the gap open
(bench.atlas sheets 20k, seeds 0 / 1: F 0.960 / 0.928 -> 0.979 / 0.960, the gap's mid-plane
outside the mesh 0 -> 92 % / 68 %).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .faithfulness import signed_residuals
from .join import ExteriorProbe, exterior_votes
from .kdtree import QUERY_THREADS

#: A chart faces out of the object when its exterior vote (`join.exterior_votes`) is this clear.
VOTE_LIMIT = 0.5
#: Input points farther than this (median spacings) from every joined sample are uncharted...
UNCHARTED = 1.0
#: ... and than this many times the noise (the charts' median residual RMS: `chart_noise`),
#: which at σ 1 % exceeds a spacing: the noise's tails are no data left out. They were taken
#: for it, and solids joined with thin shells inside them (bench.atlas 20k, σ 1 %, seed 0, before
#: / after: chair F 0.583 / 0.951; torus Chamfer 0.454 / 0.186; figurine Euler -36 / 0, 2
#: asked; mug -2 / 0, 0 asked, F 0.915 / 0.960; bench.scanned bunny -28 / 2, Chamfer 0.898 /
#: 0.392 against Poisson's 0.640; the sheets, tray, relief and hollow bust unchanged). At
#: σ 0.5 % twice the noise is over a spacing only for the figurine (1.05 spacings: Chamfer
#: 0.164 / 0.163), the dragon (1.03: 0.345 / 0.344) and the hollow bust (1.06: the same).
UNCHARTED_NOISE = 2.0
#: A chart facing out is a thin part charted on one face when uncharted points lie behind this
#: share of its samples (`behind_share`; seed 0 / 1 share 0.04: sheets F 0.980 / 0.964, 0.09:
#: 0.978 / 0.956): its far face, left out by the sheet graph (points between two sheets join
#: neither), faces a gap. bench.atlas 20k seed 0 (1 for sheets): the plates' charts
#: 0.06-0.14, no chart of mug, figurine, hook, torus over 0.051 (figurine's curled ears,
#: already shells, up to 0.09), nor at seed 1 (figurine 0.049, mug 0.049 beside one small
#: chart: `THIN_POINTS`).
THIN_SHARE = 0.06
#: Behind a sample: between these many voxels deep (the noise's near side is no evidence). An
#: uncharted point lies beyond `uncharted_reach`, so where twice the noise exceeds about 1.6
#: spacings (3.2 voxels at the default voxel, half a spacing) none lies here and no chart is
#: found thin: at such noise (σ 1 %) close sheets merge anyway (bench.atlas --noise 0.01).
THIN_DEPTH = (1.0, 3.0)
#: ... and straight behind it: within this many voxels of its normal line (as `_FRONT` in
#: `reconstruct.closed_grid` is straight in front). A thin part's far face lies under its
#: charted face (sheets 20k seeds 0 / 1: the plates' uncharted points 0.6 voxel off that line,
#: median, 2.2 voxels deep); data round the curve of a part from the border of the chart of
#: its outer face lies aside as far as it is deep (a convex surface of radius r voxels is one
#: voxel deep sqrt(2 r - 1) voxels aside). Mug 20k seed 5: the handle's outer chart (radius
#: 4 voxels) had uncharted points of the handle's sides 2.0 voxels aside, median, 2.0 deep,
#: share 0.125 (0.016 straight behind); joined as a thin part's shell, kept open against the
#: handle's core, it left Euler -14 against 0. Mug seeds 0-4, the largest share of a chart
#: facing out 0.046-0.112 without, 0.017-0.051 with (the count guards the rest); the plates'
#: charts keep theirs but for one at 0.061 on the limit (sheets seed 1, 0.050 with).
THIN_LATERAL = 1.0
#: ... and at least this many uncharted points behind it (a small chart's share is noise: mug
#: 20k seed 1, a 132-point chart at 0.118 was shelled, Euler -2 against 0; sheets seed 0 / 1
#: F 0.980 / 0.962 without, 0.979 / 0.960 with 25, 0.976 / 0.957 with 50).
THIN_POINTS = 25
#: The cloud is closed when charts facing clearly out hold this share of the join's samples.
CLOSED_SHARE = 0.5
#: ... at a seal of twice the band, tried when the band leaves the cloud open, when also the
#: charts still seen from both sides hold less than this share: the outside came in through
#: a thin part's unseen ends (a 3 mm tube sampled on its side only, 3,000 points: none
#: two-sided at the wider seal; joined closed, Euler 2), not through holes in the data round
#: a part whose inside no view saw (two 36-view scans' clouds, mug and hook: 42 % and 13 %;
#: before this share was asked, they were joined closed, Euler -118 with slots through the
#: mug's walls, and -16; now open, as the scans' own meshes are: -75 and -35).
WIDER_SEAL_TWO_SIDED = 0.05
#: A cloud is closed too when charts seen from both sides whose points lie in two layers about
#: their mesh (`faithfulness.LAYERED_KURTOSIS`: walls thinner than the noise, sampled on both
#: faces and charted once, through their middle) hold this share of the samples, with charts
#: facing out (`MIXED_SHARE`): they are joined as thin shells. A mug's 4 mm wall at σ 1 % of the
#: diagonal (1.7 mm; 20k points): 51 % layered, 17 % facing out; joined open, F 0.38 and
#: Chamfer 1.57 against Poisson's 0.80 and 1.01. A tray's 2 mm walls at σ 0.5 % (0.72 mm):
#: 71 %, 9 %; open, F 0.96 and Chamfer 0.86 against 0.94 and 0.63. Open clouds: a relief, a
#: plate with a handle, a pleated sheet, an open corner, a mug on a table top: 0-4 % layered;
#: a sheet with a solid rim under uniform noise (one layer's kurtosis: 1.8), 19 %.
LAYERED_SHARE = 0.35
#: The share of the samples that charts facing out must hold for the cloud to be closed by its
#: layered charts, or, when they are not layered but seen from both sides (`MIXED` with those),
#: to be said to be *mixed*: joined open with a warning, as an open sheet beside a solid part
#: (a plate with a handle: 12 % facing out, 87 % two-sided; joined closed, Chamfer 0.30 -> 1.14)
#: looks like a closed object with walls thinner than the noise whose layers do not show.
MIXED_SHARE = 0.05
MIXED = 0.8
#: A chart is a thin part charted on both its faces, fitted between them (two plates 1.5 mm thick
#: and 3 mm apart at σ 0.3 mm, 20k points, spacing 1.8 mm: each plate one chart, its mesh
#: midway; joined as two one-sided sheets, the gap between them was filled, 0 % of its
#: mid-plane open), when this share of its points lie in two layers about its mesh: the
#: signed distances of their `LAYER_NEIGHBOURS` nearest points of the chart to its mesh
#: spread over `LAYER_SPREAD` voxels with a kurtosis under `LAYER_KURTOSIS` (two peaks; one
#: Gaussian layer: 3, 64 draws under 2.0 in about 2 % of neighbourhoods). The plates' charts
#: at σ 0.2 / 0.3 / 0.4 % of the diagonal: 0.69-0.82 / 0.52-0.56 / 0.18-0.24 (at 0.4 % left
#: merged; at 0.5 % the sheet graph leaves one face out and `thin_charts` finds them); at σ
#: 0.5 % no chart of mug, torus, figurine or hook over 0.07, of sheets 0.13, but the chair's
#: 0.16-0.18: a chart wrapped round its 7 mm legs' edges runs inside at the edges and outside
#: between them (at 0.15 three were joined as thin parts: denoise 0.60, Chamfer over
#: Poisson's).
LAYER_SHARE = 0.3
LAYER_NEIGHBOURS = 64
LAYER_KURTOSIS = 2.0
LAYER_SPREAD = 0.5


def uncharted_reach(spacing: float, noise: float | None = None) -> float:
    """How far from every joined sample an input point is uncharted: `UNCHARTED` ``spacing``,
    or `UNCHARTED_NOISE` times the ``noise`` (`chart_noise`; None: not measured) if farther."""
    return max(UNCHARTED * spacing, 0.0 if noise is None else UNCHARTED_NOISE * noise)


def chart_noise(residuals) -> float:
    """The charts' noise: the median over the charts of the RMS of their points' signed
    ``residuals`` (c arrays) from their meshes (`residual_detail.ResidualDetail`'s)."""
    rms = [np.sqrt(np.mean(np.square(r))) for r in residuals if len(r)]
    return float(np.median(rms)) if rms else 0.0


def uncharted_points(points, samples, spacing: float, tree: cKDTree | None = None,
                     reach: float | None = None):
    """The ``points`` (n, 3) farther than ``reach`` (default `UNCHARTED` ``spacing``:
    `uncharted_reach`) from every one of ``samples`` (m, 3), in clusters of at least 4 within 2
    spacings: data the charts left out (a junction where the sheet graph cut its points off),
    not single noisy points. ``tree``: a cKDTree of ``samples`` if the caller has one. Returns
    (p, 3)."""
    tree = cKDTree(samples) if tree is None else tree
    reach = uncharted_reach(spacing) if reach is None else reach
    far = points[tree.query(points, distance_upper_bound=reach * (1 + 1e-9),
                            workers=QUERY_THREADS)[0] > reach]
    return _crowded(far, spacing)


class UnchartedTracker:
    """`uncharted_points` of one cloud ``points`` (n, 3) for samples that change a little
    between calls (a re-mesh's join): given the samples that moved since the last call, only
    the points within reach of one are looked up again. The same points as `uncharted_points`
    with ``reach`` (`uncharted_reach`; None: `UNCHARTED` ``spacing``); a torus 22k re-mesh that
    moves two samples: 1 ms instead of 7 ms."""

    def __init__(self, points: np.ndarray, spacing: float, reach: float | None = None):
        self.points = points
        self.spacing = spacing
        self.reach = uncharted_reach(spacing) if reach is None else reach

    def __call__(self, samples: np.ndarray, tree: cKDTree, moved=None) -> np.ndarray:
        """samples (m, 3) and their ``tree``; ``moved`` (q, 3) the samples added and removed
        since the last call (None: look at every point). Returns the uncharted points (p, 3)."""
        reach = self.reach
        last = self.__dict__.get("_last")
        if last is None or moved is None or len(moved) > _MOVED_SHARE * len(samples):
            far = tree.query(self.points, distance_upper_bound=reach * (1 + 1e-9),
                             workers=QUERY_THREADS)[0] > reach
        else:
            far = last[0].copy()
            if len(moved):
                near = self._near(moved, reach * (1 + 1e-6))
                far[near] = tree.query(self.points[near], distance_upper_bound=reach * (
                    1 + 1e-9))[0] > reach
        if last is not None and np.array_equal(far, last[0]):
            uncharted = last[1]
        else:
            uncharted = _crowded(self.points[far], self.spacing)
        self._last = (far, uncharted)
        return uncharted

    def _near(self, moved: np.ndarray, reach: float) -> np.ndarray:
        """(k,) indices of the points in the cells of side ``reach`` next to a ``moved`` sample's
        (q, 3): every point within ``reach`` of one, and some more (figurine 22k, 1,800 moved
        samples: 3 ms with their new look-up, against 18 for cKDTree's balls, lists of lists)."""
        if self.__dict__.get("_cells", (None,))[0] != reach:
            low = self.points.min(axis=0)
            cells = np.floor((self.points - low) / reach).astype(np.int64)
            self._cells = (reach, low, cells.max(axis=0) + 5, cells + 2)  # two cells to spare
        _, low, shape, cells = self._cells
        at = np.floor((moved - low) / reach).astype(np.int64) + 2
        at = at[np.all((at >= 1) & (at < shape - 1), axis=1)]  # beyond: farther from every point
        marked = np.zeros(tuple(shape), bool)
        marked[tuple((at[:, None, :] + _NEIGHBOUR_CELLS).reshape(-1, 3).T)] = True
        return np.flatnonzero(marked[tuple(cells.T)])


#: (27, 3) a cell and its neighbours, as offsets.
_NEIGHBOUR_CELLS = np.stack(np.meshgrid(*[(-1, 0, 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
#: Beyond this share of the samples moved, `UnchartedTracker` looks every point up again.
_MOVED_SHARE = 0.1


def _crowded(far: np.ndarray, spacing: float) -> np.ndarray:
    """The ``far`` points (p, 3) in clusters of at least 4 within 2 ``spacing``."""
    if len(far) < 4:
        return far[:0]
    crowd = cKDTree(far).query_ball_point(far, 2 * spacing, return_length=True)
    return far[crowd >= 4]


def behind_share(chart_samples, chart_normals, points, spacing: float, voxel: float,
                 far=None, tree: cKDTree | None = None, reach: float | None = None):
    """(c,) uncharted points (`uncharted_points` of ``points`` (n, 3) with ``reach``; ``far``
    (p, 3) and a ``tree`` of the charts' samples, in order, if the caller has them) lying
    `THIN_DEPTH` voxels straight behind (`THIN_LATERAL`) their nearest sample of each chart
    (against its outward normal), per sample of the chart.
    chart_samples, chart_normals : c arrays (m_i, 3)."""
    sizes = np.array([len(s) for s in chart_samples], float)
    filled = [i for i, s in enumerate(chart_samples) if len(s)]
    if not filled:
        return np.zeros(len(chart_samples))
    every = np.concatenate([chart_samples[i] for i in filled])
    facing = np.concatenate([chart_normals[i] for i in filled])
    owner = np.concatenate([np.full(len(chart_samples[i]), i) for i in filled])
    tree = cKDTree(every) if tree is None else tree
    far = uncharted_points(points, every, spacing, tree, reach) if far is None else far
    if len(far) == 0:
        return np.zeros(len(chart_samples))
    distance, nearest = tree.query(far)
    depth = -np.einsum("ij,ij->i", far - every[nearest], facing[nearest])
    lateral = np.sqrt(np.maximum(distance**2 - depth**2, 0.0))
    behind = ((depth > THIN_DEPTH[0] * voxel) & (depth < THIN_DEPTH[1] * voxel)
              & (lateral <= THIN_LATERAL * voxel))
    counts = np.bincount(owner[nearest[behind]], minlength=len(chart_samples))
    return counts / np.maximum(sizes, 1.0)


def two_layer_charts(meshes, chart_points, points, voxel: float) -> np.ndarray:
    """(c,) bool: charts whose ``meshes`` run between two layers of their own points over
    `LAYER_SHARE` of them (``chart_points``: c index arrays into ``points`` (n, 3); ``voxel``
    the join's grid spacing): a part thinner than the point spacing, charted on both its
    faces."""
    layered = np.zeros(len(meshes), bool)
    for i, (mesh, members) in enumerate(zip(meshes, chart_points, strict=True)):
        own = points[np.asarray(members)]
        if len(own) <= LAYER_NEIGHBOURS or len(mesh.vertices) == 0:
            continue
        signed = signed_residuals(mesh, own, QUERY_THREADS)
        near = signed[cKDTree(own).query(own, k=LAYER_NEIGHBOURS, workers=QUERY_THREADS)[1]]
        centred = near - near.mean(axis=1, keepdims=True)
        variance = np.mean(centred**2, axis=1)
        kurtosis = np.mean(centred**4, axis=1) / np.maximum(variance**2, 1e-300)
        two = (kurtosis < LAYER_KURTOSIS) & (np.sqrt(variance) > LAYER_SPREAD * voxel)
        layered[i] = two.mean() >= LAYER_SHARE
    return layered


def thin_charts(outward, behind, sizes, chart_points) -> np.ndarray:
    """(c,) bool charts of a thin part: facing out (``outward`` (c,) bool) with `THIN_SHARE`
    of uncharted points ``behind`` (c,) their ``sizes`` (c,) samples, `THIN_POINTS` of them at
    least; and, spreading from those, charts beside one (sharing input points: ``chart_points``,
    c index arrays) with that share behind, however small. The count guards against a lone
    small chart's noise, and the plates' rims and their junction with the foot are charted in
    pieces of 100–250 samples (bench.atlas sheets 20k, seeds 0 / 1: the gap's mid-plane outside
    the mesh 93.4 / 67.3 % -> 94.2 / 68.7 %; no chart of the other objects is thin, so none
    spreads)."""
    thin = outward & (behind >= THIN_SHARE) & (behind * sizes >= THIN_POINTS)
    candidates = outward & (behind >= THIN_SHARE) & ~thin
    if not (thin.any() and candidates.any()):
        return thin
    owners = [set(np.asarray(members).tolist()) for members in chart_points]
    while True:
        joined = [i for i in np.flatnonzero(candidates & ~thin)
                  if any(not owners[i].isdisjoint(owners[j]) for j in np.flatnonzero(thin))]
        if not joined:
            return thin
        thin[joined] = True


class ChartSides:
    """Decide the sides of an atlas's charts (see the module's docstring).

    Parameters: ``band`` the join's band (voxels; ``2 band`` is tried as the seal too);
    ``closed`` None to decide, or True / False to impose.

    Fitted: ``closed_`` bool, ``layered_`` the share of the samples in layered charts seen
    from both sides when they closed the cloud (`LAYERED_SHARE`; else None), ``mixed_`` the
    (outward, two-sided) shares of a cloud joined open that may be closed with walls thinner
    than the noise (`MIXED`; else None), ``seal_`` the exterior grid's band, ``probe_`` its
    `join.ExteriorProbe`, ``votes_`` (c,) in [−1, 1],
    ``turns_`` (c,) ±1 turning each chart's normals to face out, ``shells_`` (c,) bool charts
    joined as a thin closed shell (two-sided, or thin), ``thin_`` (c,) bool thin parts whose
    shell's far face keeps the gap in front of it open, ``open_pieces_`` the share of the
    samples in shells of a closed cloud's pieces apart from the rest with no chart facing out
    (an open sheet beside a closed object: `_apart_two_sided`; None when none).
    """

    def __init__(self, band: float = 3.0, closed: bool | None = None):
        self.band = band
        self.closed = closed

    def fit(self, chart_samples, chart_normals, points, spacing: float, voxel: float,
            chart_points, two_layer=None, layered=None, reach: float | None = None
            ) -> ChartSides:
        """chart_samples, chart_normals : c arrays (m_i, 3) of the joined samples and their
        normals as the charts are oriented now; points : (n, 3) the input cloud; spacing : its
        median spacing; voxel : the join's grid spacing; chart_points : c index arrays into
        ``points``, each chart's points; two_layer : (c,) bool charts fitted between the two
        faces of a thin part (`two_layer_charts`; None: none), joined in a closed cloud as
        thin parts; layered : a callable giving (c,) bool, the charts whose points lie in two
        layers about their mesh (`faithfulness.LAYERED_KURTOSIS`), asked only when the votes
        leave the cloud open (None: none); reach : how far from every sample a point is
        uncharted (`uncharted_reach`; None: `UNCHARTED` spacings). Returns self."""
        sizes = np.array([len(s) for s in chart_samples], float)
        filled = [s for s in chart_samples if len(s)]
        everything = np.concatenate(filled) if filled else np.zeros((0, 3))
        tree = cKDTree(everything) if filled else None
        # (a join told to stay open uses the votes for nothing but their report)
        left_out = (uncharted_points(points, everything, spacing, tree, reach)
                    if filled and self.closed is not False else None)
        total = max(sizes.sum(), 1.0)
        tried = []
        for seal in (self.band, 2 * self.band):
            probe = ExteriorProbe(everything, voxel, seal, left_out)
            votes, two_sided = exterior_votes(chart_samples, chart_normals, voxel,
                                              probe=probe)
            outward = np.abs(votes) >= VOTE_LIMIT
            tried.append((seal, probe, votes, two_sided, outward))
            closed = bool(sizes[outward].sum() >= CLOSED_SHARE * total)
            if seal > self.band:  # the wider seal: only when it leaves few charts two-sided
                closed &= bool(sizes[~outward & (two_sided >= VOTE_LIMIT)].sum()
                               < WIDER_SEAL_TWO_SIDED * total)
            if self.closed is not None:
                closed = bool(self.closed)
            if closed or self.closed is not None:
                break
        if not closed:  # the votes at the band say why it is open
            seal, probe, votes, two_sided, outward = tried[0]
        self.layered_ = self.mixed_ = self.open_pieces_ = None
        if not closed and self.closed is None:
            facing = sizes[outward].sum() / total
            both = ~outward & (two_sided >= VOTE_LIMIT)
            if facing >= MIXED_SHARE and facing + sizes[both].sum() / total >= MIXED:
                walls = both & (False if layered is None else np.asarray(layered(), bool))
                if sizes[walls].sum() >= LAYERED_SHARE * total:
                    closed, self.layered_ = True, sizes[walls].sum() / total
                else:
                    self.mixed_ = (facing, sizes[both].sum() / total)
        self.closed_, self.votes_, self.seal_, self.probe_ = closed, votes, seal, probe
        self.turns_ = np.ones(len(chart_samples))
        self.shells_ = np.zeros(len(chart_samples), bool)
        self.thin_ = np.zeros(len(chart_samples), bool)
        if closed:
            # the others keep their orientation along the overlaps, turned like most charts
            turn = np.sign(np.sum(sizes[outward] * np.sign(votes[outward]))) or 1.0
            self.turns_ = np.where(outward, np.sign(votes), turn)
            self.shells_ = ~outward & (two_sided >= VOTE_LIMIT)
            # a chart facing out with data left out just behind it: a thin part charted on one
            # face (two plates a few noise widths apart), joined as a shell whose far face
            # faces that data and keeps the gap in front of it open
            behind = behind_share(chart_samples, [t * n for t, n in zip(
                self.turns_, chart_normals, strict=True)], points, spacing, voxel, left_out,
                tree)
            self.thin_ = thin_charts(outward, behind, sizes, chart_points)
            if two_layer is not None:  # both faces charted at once
                self.thin_ |= np.asarray(two_layer, bool)
            self.shells_ |= self.thin_
            self.open_pieces_ = _apart_two_sided(outward, self.shells_ & ~self.thin_, sizes,
                                                 chart_points, len(points))
        return self


def _apart_two_sided(outward, shells, sizes, chart_points, n_points: int) -> float | None:
    """The share of the samples (``sizes`` (c,) per chart) in the ``shells`` (c,) bool of pieces
    of charts (charts that share points, ``chart_points`` c index arrays into ``n_points``)
    where no chart is ``outward`` (c,) bool: seen from both sides all over, apart from the
    volume the rest closes. A thin part's shells (an ear) share points with charts that face
    out; an open sheet beside a closed object (a sphere and a sheet in one cloud: the sheet
    joined as a slab 10 noise widths thick) shares none. None when there is none."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    chart = np.repeat(np.arange(len(chart_points)), [len(m) for m in chart_points])
    point = np.concatenate([np.asarray(m, np.int64) for m in chart_points])
    incidence = coo_matrix((np.ones(len(point)), (chart, point)),
                           shape=(len(chart_points), n_points)).tocsr()
    _, piece = connected_components(incidence @ incidence.T, directed=False)
    facing = np.bincount(piece, outward.astype(float)) > 0
    apart = shells & ~facing[piece]
    share = float(sizes[apart].sum() / max(sizes.sum(), 1.0))
    return share if share > 0 else None
