"""The signed grid of a closed join, kept between re-meshes and re-evaluated only round the
samples that changed.

A closed join (`reconstruct.join.implicit_mesh`) signs every node of a grid round its samples:
1. *occupied*: the cells holding a sample or a data point no chart represents;
2. *free*: the nodes farther than the seal from every occupied cell (a distance transform);
3. *exterior*: the free nodes connected to the grid's border, or in an enclosed pocket that the
   nearest samples' tangent planes mostly put in front, unless nearly as near samples' planes
   put it behind (`reconstruct.grid_steps.exterior_of`, ``VOTE_MARGIN``);
4. the *closing* of the samples by the seal (Serra 1982): seal voxels in from the exterior, so
   a gap between charts narrower than twice the seal is capped near its data;
5. near the samples (the nodes not free) the implicit moving-least-squares distance of their
   tangent planes (Kolluri 2005), blended into the closing (`_TRUSTED`, `_FRONT`);
6. a grey opening and a Gaussian smoothing (`_OPEN`, `_SMOOTH`).

Steps 1 and 3 look at the whole grid; the others are local, each within a known number of
voxels (the steps on whole grids or boxes of them are `reconstruct.grid_steps`).
`ClosedSDF.update` redoes 1 and 3 over the grid (cheap: a rounding, a labelling and a vote) and
the local steps in boxes round what changed, wide enough that the result equals a fresh
`ClosedSDF.fit` node for node (tested). A re-mesh that moves two samples of a torus's 21,000
re-evaluated its whole grid before (0.9–1.5 s of a 1.1–1.7 s re-mesh).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy import ndimage

from .grid_steps import (
    VOTE_MARGIN,
    boxes_round,
    cell_reach,
    farther_than,
    flat_of,
    free_pockets,
    grey_opening3,
    grown,
    occupancy,
    pockets_outside,
    squared_distance,
    voter_sides,
)
from .kdtree import QUERY_THREADS, PointTree
from .marching import KeptMarch
from .sdf_grid import (
    changed_rows,
    imls,
    kept_mesh_arrays,
    lattice_box,
    restore_kept_mesh,
    union,
)

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
#: Voxels of the smoothed grid a change of the blended one reaches: the opening's erosion and
#: dilation, then the Gaussian's radius (scipy's: truncate 4 · σ, rounded).
_SMOOTH_REACH = 2 * (_OPEN // 2) + int(4.0 * _SMOOTH + 0.5)
#: An update that changes more than this share of the samples is a fresh fit.
_MOST = 0.25
#: Voxels by which the smoothed grid stays off the level: a value nearer it is set to this far,
#: on its side (the surface moves by as much at most). Marching cubes puts the vertex of an edge
#: with an end that near its level on that node (float32), where several edges share it, and the
#: march can then not be followed between re-meshes (`reconstruct.marching`): the hook's grid
#: (1.6 million nodes) was marched whole every time, 74-80 ms; now 26 ms.
_OFF_LEVEL = 1e-3
#: Voxels within which an update looks for the nodes whose eighth nearest sample is nearer
#: than that (the others, farther from the samples, are all looked at): sheets 22k, 2,300
#: samples moved, 114,000 nodes queried before, 61,000 with this.
_LOCAL = 4.0
#: Voxels the grid's box spares beyond the seal's pad on every side, on the lattice
#: ``voxel · ℤ³``. The box is kept while the samples fit in it with the pad: a new λ moves a
#: chart's outline and often an extreme sample by a fraction of a voxel, which shifted a box
#: fitted tightly round the samples and made every such re-mesh a fresh fit (hook 22k: 4 of 4
#: re-meshes, about 202,700 nodes' planes and 0.6-1.1 s of its join; now about 10,000 nodes).
BOX_SLACK = 2


class ClosedSDF:
    """The signed grid of a closed join on a box of the lattice ``voxel · ℤ³`` round the
    samples (`BOX_SLACK`), kept by `fit` and `update` while the samples fit in it.

    Parameters: ``voxel`` grid spacing; ``band`` the planes' distance is clipped to ``band + 1``
    voxels by the closing; ``seal`` voxels (gaps narrower than twice this are capped; default
    ``band``); ``tolerance`` how far (input units; default 1e-9 voxels) a sample or normal may
    move and still count as the same in `update`; ``shift`` voxels by which the lattice is
    moved along every axis (a topology that depends on it: `reconstruct.join_alignment`).

    Fitted attributes: ``origin_`` (3,), ``shape_`` (3,), ``values_`` (shape) float32 the
    smoothed signed grid (positive outside) for marching cubes, ``samples_`` (m, 3), ``normals_``
    (m, 3), ``kept_open_`` (m,), ``tree_``, ``n_changed_`` samples added and removed by the
    last fit or update, ``n_evaluated_`` nodes whose planes it evaluated.
    """

    def __init__(self, voxel: float, band: float = 3.0, seal: float | None = None,
                 tolerance: float | None = None, shift: float = 0.0):
        self.voxel = voxel
        self.band = band
        self.seal = seal
        self.tolerance = tolerance
        self.shift = shift

    @property
    def _params(self) -> tuple:
        return self.voxel, self.band, self.seal, self.tolerance, self.shift

    @property
    def _seal(self) -> float:
        return self.band if self.seal is None else self.seal

    def follow(self, samples, normals, kept_open=None, uncharted=None) -> ClosedSDF:
        """`update` when fitted with the present parameters, else `fit`. Returns self."""
        if getattr(self, "_fitted_with", None) == self._params:
            return self.update(samples, normals, kept_open, uncharted)
        return self.fit(samples, normals, kept_open, uncharted)

    def fit(self, samples, normals, kept_open=None, uncharted=None) -> ClosedSDF:
        """samples, normals : (m, 3); kept_open : (m,) bool samples whose front the opening may
        not fill (`reconstruct.join.implicit_mesh`); uncharted : (p, 3) data points no chart
        represents, or a callable of the samples' `kdtree.PointTree` and of the samples (q, 3)
        added and removed since its last call (None: all are new) giving them. The box fitted
        or loaded last is kept if it holds the samples with the seal's pad. Returns self."""
        self._take(samples, normals, kept_open)
        return self._fit_taken(uncharted)

    def _fit_taken(self, uncharted) -> ClosedSDF:
        """`fit` to the samples `_take` kept."""
        seal, voxel = self._seal, self.voxel
        if not self._holds(self.samples_):
            shift = self.shift % 1.0  # the low side spares a voxel more when shifted
            origin, self.shape_ = lattice_box(self.samples_, voxel,
                                              seal + 3 + BOX_SLACK + (shift > 0))
            self.origin_ = origin + shift * voxel
        shape = tuple(int(n) for n in self.shape_)
        extra = uncharted(self.tree_, None) if callable(uncharted) else uncharted
        self._occupied = occupancy(self.samples_, extra, self.origin_, self.shape_, voxel)
        self._free = farther_than(self._occupied, seal)
        self._pockets = free_pockets(self._free)
        self._voting = self._vote()
        self._outside = pockets_outside(self._pockets, self._voting[1])
        self._exterior = self._outside[self._pockets[0]] & self._free
        self._closing = self._closing_of(self._exterior)
        self._planes, self._nearest, self._ahead, self._eighth = (np.zeros(shape)
                                                                  for _ in range(4))
        self._held = np.zeros(shape, bool)
        near = np.flatnonzero(~self._free)
        self._evaluate(near)
        self._reach = float(self._eighth.max(initial=0.0))
        self._values = self._closing.copy()
        self._blend_at(near)
        self.values_ = self._smoothed(self._values, self._holding(tuple(slice(0, n)
                                                                        for n in shape)))
        self.n_changed_, self.n_evaluated_ = len(self.samples_), len(near)
        self._fitted_with = self._params
        return self

    def update(self, samples, normals, kept_open=None, uncharted=None) -> ClosedSDF:
        """Move to new samples (same arguments as `fit`), re-evaluating only round those that
        changed; a fresh `fit` when the samples leave the grid's box or most of them changed."""
        old, old_normals, old_open, old_tree = (self.samples_, self.normals_, self.kept_open_,
                                                self.tree_)
        self._take(samples, normals, kept_open)
        added, removed = changed_rows(old, old_normals, old_tree, self.samples_, self.normals_,
                                      self._tolerance, self.voxel, old_open, self.kept_open_)
        changed = int(added.sum() + removed.sum())
        if changed == 0:
            self.n_changed_ = self.n_evaluated_ = 0
            return self
        if (not hasattr(self, "_occupied") or changed > _MOST * (len(old) + len(samples))
                or not self._holds(self.samples_)):
            self._fit_taken(uncharted)  # (the samples taken and their tree built above)
            self.n_changed_ = changed
            return self
        moved = np.concatenate([self.samples_[added], old[removed]])
        extra = uncharted(self.tree_, moved) if callable(uncharted) else uncharted
        occupied = occupancy(self.samples_, extra, self.origin_, self.shape_, self.voxel)
        cells = np.flatnonzero(occupied != self._occupied)
        self._occupied = occupied
        flipped = self._update_free(cells)
        # the planes round the moved samples do not depend on the pockets, their votes or the
        # closing: evaluated in a thread meanwhile, as numpy and pykdtree release the GIL (mug
        # and figurine 22k, medians of 24 re-meshes: the join 210 -> 194 ms, 178 -> 162 ms)
        with ThreadPoolExecutor(1, thread_name_prefix="closed-grid-planes") as thread:
            planes = thread.submit(self._update_planes, moved, flipped)
            closed = self._update_exterior(moved, flipped)
            evaluated = planes.result()
        touched = union([evaluated, closed, flipped])
        self._blend_at(touched)
        self._update_smoothed(touched)
        self.n_changed_, self.n_evaluated_ = changed, len(evaluated)
        return self

    # -- the steps -----------------------------------------------------------------------------
    def _take(self, samples, normals, kept_open) -> None:
        """Keep copies of the arrays (an `update` compares the next ones with them: a caller's
        array changed in place would hide its change)."""
        self.samples_ = np.array(samples, float, order="C")
        self.normals_ = np.array(normals, float, order="C")
        self.kept_open_ = (np.zeros(len(self.samples_), bool) if kept_open is None
                           else np.array(kept_open, bool))
        self.tree_ = PointTree(self.samples_)

    def _holds(self, samples: np.ndarray) -> bool:
        """Whether the box kept (``origin_``, ``shape_``, for the present parameters) holds
        ``samples`` (m, 3) with the seal's pad to spare on every side."""
        if "origin_" not in vars(self) or getattr(self, "_fitted_with", None) != self._params:
            return False
        pad = (self._seal + 3) * self.voxel
        return bool(np.all(samples.min(axis=0) - pad >= self.origin_) and np.all(
            samples.max(axis=0) + pad <= self.origin_ + self.voxel * (self.shape_ - 1)))

    def _vote(self, moved=None, before=None) -> tuple:
        """`voter_sides` of the pockets' voters (None, None without any): all, or with
        ``moved`` samples (q, 3) and the voters and votes ``before`` the samples moved, only
        the new voters and those a moved one is within `VOTE_MARGIN` voxels of as near as
        their nearest was (the samples that vote may have changed); the others keep their
        vote (a voter is chosen by its place: `grid_steps.pocket_voters`)."""
        voters = self._pockets[2]
        if voters is None:
            return None, None
        at = self.origin_ + self.voxel * voters[0]
        if moved is None or before is None or before[0] is None:
            return voter_sides(at, self.samples_, self.normals_, self.tree_, self.voxel)
        (_, _, was), (old_distance, old_front) = before
        flat = voters[2]
        index = np.minimum(np.searchsorted(was, flat), len(was) - 1)  # both ascending
        known = was[index] == flat
        distance = np.where(known, old_distance[index], np.inf)
        front = np.where(known, old_front[index], False)
        reach = distance + VOTE_MARGIN * self.voxel
        bound = float(reach[known].max(initial=0.0)) * (1 + 1e-9)
        again = ~known
        if known.any():
            again[known] = PointTree(moved).query(at[known], distance_upper_bound=bound,
                                                workers=QUERY_THREADS)[0] <= reach[known]
        if again.any():
            distance[again], front[again] = voter_sides(at[again], self.samples_,
                                                        self.normals_, self.tree_, self.voxel)
        return distance, front

    @property
    def _tolerance(self) -> float:
        return 1e-9 * self.voxel if self.tolerance is None else self.tolerance

    def _closing_of(self, exterior: np.ndarray) -> np.ndarray:
        """The closing's signed distance (clipped to ±(band + 1) voxels) on ``exterior``'s grid."""
        limit = (self.band + 1) * self.voxel
        if not exterior.any():
            return np.full(exterior.shape, -limit)
        # beyond seal + band + 1 voxels the value is clipped: the distance is needed only within
        squared = squared_distance(exterior, self._seal + self.band + 1)
        # the value of each squared distance (a few hundred at most), looked up
        value = np.clip(self._seal * self.voxel
                        - self.voxel * np.sqrt(np.arange(int(squared.max()) + 1.0)), -limit, limit)
        return value[squared]

    def _evaluate(self, flat: np.ndarray) -> None:
        """The planes' distance at the nodes ``flat``, and what the blend and the opening need
        of their nearest sample (how far, how far in front, whether kept open)."""
        if len(flat) == 0:
            return
        index = np.column_stack(np.unravel_index(flat, tuple(self.shape_)))
        nodes = self.origin_ + self.voxel * index.astype(float)
        planes, distance, neighbours = imls(nodes, self.samples_, self.normals_, self.tree_,
                                            self.voxel, return_index=True)
        nearest = neighbours[:, 0]
        self._planes.flat[flat] = planes
        self._nearest.flat[flat] = distance[:, 0]
        self._eighth.flat[flat] = distance[:, -1]
        self._ahead.flat[flat] = np.einsum("gi,gi->g", nodes - self.samples_[nearest],
                                           self.normals_[nearest])
        self._held.flat[flat] = self.kept_open_[nearest]

    def _front(self, planes, nearest, ahead) -> np.ndarray:
        """Whether a node lies straight in front of its nearest sample, outside the planes."""
        lateral = np.sqrt(np.maximum(nearest**2 - ahead**2, 0.0))
        return (ahead > 0) & (lateral <= _FRONT * self.voxel) & (planes > 0)

    def _blend_at(self, flat: np.ndarray) -> None:
        """The blended grid at the nodes ``flat``: the closing, and near the samples the planes
        within `_TRUSTED` voxels of one (or straight in front of one), the closing from a
        voxel further on."""
        closing = self._closing.flat[flat]
        near = ~self._free.flat[flat]
        at = flat[near]
        planes, nearest = self._planes.flat[at], self._nearest.flat[at]
        blend = np.clip(nearest / self.voxel - _TRUSTED, 0.0, 1.0)
        blend[self._front(planes, nearest, self._ahead.flat[at])] = 0.0
        closing[near] = (1 - blend) * planes + blend * closing[near]
        self._values.flat[flat] = closing

    def _holding(self, box: tuple[slice, ...]) -> np.ndarray:
        """(box) bool: nodes straight in front of a kept-open sample, which the opening may not
        fill."""
        held = ~self._free[box] & self._held[box]
        at = np.nonzero(held)  # few: the nodes near kept-open samples
        held[at] = self._front(self._planes[box][at], self._nearest[box][at],
                               self._ahead[box][at])
        return held

    def _smoothed(self, values: np.ndarray, held: np.ndarray) -> np.ndarray:
        """``values`` opened, smoothed and kept off the level (`_OFF_LEVEL`), in float32: what
        marching cubes takes (the opening and the Gaussian read and write half the bytes:
        mug 22k, a 0.9-million-node grid: 33-39 -> 20 ms a re-mesh)."""
        values = values.astype(np.float32)
        if _OPEN:
            opened = (grey_opening3(values) if _OPEN == 3
                      else ndimage.grey_opening(values, size=(_OPEN,) * 3))
            opened[held] = np.maximum(opened[held], values[held])
            values = opened
        if _SMOOTH:
            values = ndimage.gaussian_filter(values, _SMOOTH)
        floor = np.float32(_OFF_LEVEL * self.voxel)
        near_level = np.abs(values) < floor
        values[near_level] = np.where(values[near_level] < 0, -floor, floor)
        return values

    def _update_free(self, cells: np.ndarray) -> np.ndarray:
        """Re-derive ``_free`` round the occupancy's changed ``cells``; returns the flat indices
        of the nodes whose freedom flipped."""
        reach = int(np.ceil(self._seal)) + 1
        flipped = []
        for box in boxes_round(cells, self.shape_, reach):
            outer, inner = grown(box, reach, self.shape_)
            occupied = self._occupied[outer]
            free = (farther_than(occupied, self._seal) if occupied.any()
                    else np.ones(occupied.shape, bool))[inner]
            flipped.append(flat_of(box, free != self._free[box], self.shape_))
            self._free[box] = free
        return union(flipped)

    def _update_exterior(self, moved: np.ndarray, flipped: np.ndarray) -> np.ndarray:
        """Follow the free nodes' ``flipped`` (flat indices) and the ``moved`` samples (q, 3)
        into the pockets, their votes, the exterior and its closing; returns the flat indices
        of the nodes whose closing changed."""
        before = self._pockets[2], self._voting
        if len(flipped):  # the pockets may have joined or parted
            self._pockets = free_pockets(self._free)
        self._voting = self._vote(moved, before)
        outside = pockets_outside(self._pockets, self._voting[1])
        if len(flipped) or not np.array_equal(outside, self._outside):
            self._outside = outside
            exterior = outside[self._pockets[0]] & self._free
            changed_exterior = np.flatnonzero(exterior != self._exterior)
        else:  # the same pockets, voted the same way: the same exterior
            exterior, changed_exterior = self._exterior, np.zeros(0, np.int64)
        return self._update_closing(changed_exterior, exterior)

    def _update_closing(self, changed: np.ndarray, exterior: np.ndarray) -> np.ndarray:
        """Take the new ``exterior`` and re-derive the closing round the ``changed`` nodes;
        returns the flat indices of the nodes whose closing changed."""
        self._exterior = exterior
        reach = int(np.ceil(self._seal + self.band + 1)) + 1  # beyond it the closing is clipped
        touched = []
        for box in boxes_round(changed, self.shape_, reach):
            outer, inner = grown(box, reach, self.shape_)
            closing = self._closing_of(exterior[outer])[inner]
            touched.append(flat_of(box, closing != self._closing[box], self.shape_))
            self._closing[box] = closing
        return union(touched)

    def _update_planes(self, moved: np.ndarray, flipped: np.ndarray) -> np.ndarray:
        """Evaluate the planes again where the 8 nearest samples may have changed (nodes nearer
        a ``moved`` sample (q, 3) than their 8th nearest was) and where a node became near
        (``flipped``); clear them where one stopped being near. Returns the evaluated nodes."""
        gone = flipped[self._free.flat[flipped]]
        for grid in (self._planes, self._nearest, self._ahead, self._eighth):
            grid.flat[gone] = 0.0
        self._held.flat[gone] = False
        cells = np.floor((moved - self.origin_) / self.voxel).astype(np.int64)
        cells = np.clip(cells, 0, self.shape_ - 1)
        # most nodes' eighth nearest is within _LOCAL voxels: such a node can be nearer a moved
        # sample only within _LOCAL + √3 voxels of the sample's cell (a ball, not a box of
        # blocks: mug 22k, 3,000 samples moved, 100,000 nodes queried before, 45,000 with this)
        reach = int(np.ceil(self._reach / self.voxel)) + 1
        ball = _LOCAL + np.sqrt(3.0)
        candidates = []
        tree = PointTree(moved)
        for box in boxes_round(np.ravel_multi_index(tuple(cells.T), tuple(self.shape_)),
                               self.shape_, reach):
            low, high = np.array([[s.start, s.stop] for s in box]).T
            at_moved = np.zeros(tuple(high - low), bool)
            inside = np.all((cells >= low) & (cells < high), axis=1)
            at_moved[tuple((cells[inside] - low).T)] = True
            eighth = self._eighth[box]
            near = ~self._free[box] & (eighth > 0)  # near before and after
            # a sample that moved within the tolerance (a chart's vertex a bit apart between
            # two re-meshes) kept its nodes' distances: a node's eighth may be off by as much
            # (figurine 22k: such a sample removed later, a node 1 ulp farther from it than its
            # eighth kept its planes, and the mesh back at the fitted λ was not the fit's)
            slack = 2 * self._tolerance
            # a node nearer a moved sample than its eighth lies within its eighth + √3 voxels
            # of the sample's cell (mug 22k: 69,000 nodes queried with the ball, 47,000 with
            # this; ``squared`` is exact within the ball, beyond it only larger)
            squared = squared_distance(at_moved, ball)
            limit = cell_reach(np.minimum((eighth + slack) / self.voxel, _LOCAL))
            marked = squared <= limit * limit
            flat = flat_of(box, near & (marked | (eighth > _LOCAL * self.voxel)), self.shape_)
            index = np.column_stack(np.unravel_index(flat, tuple(self.shape_)))
            bound = self._eighth.flat[flat]
            gap = tree.query(self.origin_ + self.voxel * index.astype(float),
                             distance_upper_bound=self._reach * (1 + 1e-9) + slack,
                             workers=QUERY_THREADS)[0]
            candidates.append(flat[gap <= bound + slack])
        arrived = flipped[~self._free.flat[flipped]]
        evaluated = union([arrived, *candidates])
        self._evaluate(evaluated)
        self._reach = max(self._reach, float(self._eighth.flat[evaluated].max(initial=0.0)))
        return evaluated

    def _update_smoothed(self, touched: np.ndarray) -> None:
        """Smooth again round the nodes of the blended grid that changed (``touched``). A
        re-mesh of the mug or the sheets (22k) changes nodes all over its surface: their box
        is 90-100 % of the grid (the figurine's 26 %, the hook's 13 %). Its halves smoothed in
        two threads (the opening and ndimage's Gaussian release the GIL) took 22 -> 17 ms
        alone, but no gain showed in the join's time (2026-12-06)."""
        reach = _SMOOTH_REACH
        for box in boxes_round(touched, self.shape_, reach):
            outer, inner = grown(box, reach, self.shape_)
            self.values_[box] = self._smoothed(self._values[outer], self._holding(outer))[inner]

    def march(self) -> tuple[np.ndarray, np.ndarray]:
        """Marching cubes of ``values_`` at 0: vertices (v, 3) float32 in voxel units from
        ``origin_``, faces (f, 3), as skimage's, marched again only round the nodes that
        changed since the last call (`reconstruct.marching.KeptMarch`)."""
        if "_march" not in self.__dict__:
            self._march = KeptMarch()
        return self._march(self.values_, self.voxel)

    # -- persistence ---------------------------------------------------------------------------
    def state(self, prefix: str = "") -> tuple[dict, dict[str, np.ndarray]]:
        """The samples, the box and the last mesh (``mesh_``) as (meta, arrays named
        ``prefix`` + ...): a loaded grid gives that mesh back for the same samples and
        evaluates afresh, on the same box, for others (the whole grid would be several times
        the atlas's size)."""
        meta = {"kind": "closed", "params": {"voxel": self.voxel, "band": self.band,
                                             "seal": self.seal, "tolerance": self.tolerance,
                                             "shift": self.shift},
                "mesh_key": list(getattr(self, "mesh_key_", []))}
        arrays = {"samples": self.samples_, "normals": self.normals_,
                  "kept_open": self.kept_open_, **kept_mesh_arrays(self)}
        if "origin_" in vars(self):
            arrays.update(origin=self.origin_, shape=self.shape_)
        return meta, {prefix + name: np.asarray(value) for name, value in arrays.items()}

    @classmethod
    def from_state(cls, meta: dict, arrays: dict, prefix: str = "") -> ClosedSDF:
        """Rebuild from `state`: the same samples give back its mesh; `update` fits afresh
        on the saved box while it holds the samples."""
        self = cls(**meta["params"])
        self._take(arrays[prefix + "samples"], arrays[prefix + "normals"],
                   arrays[prefix + "kept_open"])
        if prefix + "origin" in arrays:
            self.origin_ = np.asarray(arrays[prefix + "origin"], float)
            self.shape_ = np.asarray(arrays[prefix + "shape"], np.int64)
        self.n_evaluated_ = self.n_changed_ = 0
        self._fitted_with = self._params
        restore_kept_mesh(self, meta, arrays, prefix)
        return self
