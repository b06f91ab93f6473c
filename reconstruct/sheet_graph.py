"""A neighbourhood graph that never bridges two sheets: the two sides of a thin ear, the inside
and outside of a mug wall, two plates close together.

A plain kNN graph joins points that are near in space; where two sheets lie closer than a
neighbourhood is wide, it joins the sheets and every chart, embedding or geodesic built on it
runs through both. Here each point gets a tangent plane (PCA of its ``n_layer`` nearest points)
and its neighbourhood's spread across that plane is tested for two layers: the offsets along the
normal are split in two (Otsu's split, vectorised over all points) and called layered when the
two groups lie further apart than one noisy sheet allows (``layer_ratio`` within-group widths)
and lie in parallel planes of at least three points each (not the two faces of an edge:
`LAYERS_ANGLE`). A layered point's plane and noise are then refitted on its own side only.

An edge i ~ j of the kNN graph (``n_neighbors``) is kept only when
- the unoriented normals agree within ``max_angle`` degrees,
- each point lies within ``plane_factor`` local noise widths (plus a tenth of a spacing, so a
  perfect plane still connects) of the other's plane, and
- neither point's neighbourhood put the other on its far layer, or either of them within
  ``margin`` layer widths of the split (a point midway between sheets is left unjoined).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from sklearn.base import BaseEstimator

from .neighbors import plane_fits
from .validation import check_points

#: Otsu split of 40 offsets (median of 20k draws): one Gaussian layer 2.9 within-group widths,
#: one uniform layer 3.6, two layers 3 σ apart 3.6, 4 σ apart 4.3. Averaged over a
#: neighbourhood above this, a neighbourhood is two layers.
LAYER_RATIO = 3.4
#: A point the wide test finds layered is split only where its own neighbourhood, seen along the
#: wide normal, holds two layers (its Otsu ratio above ``layer_ratio``) and its neighbours' do on
#: average above this (one layer: 2.9 median): a slab's top face, whose own neighbourhood holds
#: one layer, is left whole (bench hook 20k: points in the graph 19583 without the wide test,
#: 18726 with the own ratio alone, 19381 with both).
_WIDE_MEAN = 3.0

#: Beyond the first wide scale (`SheetGraph.n_wide`) two layers must also leave a trough between
#: them: of the wide neighbourhood's offsets, fewer lie within half a pooled width of the Otsu
#: split than within as much of the sparser layer's mean, by this share (`trough`, averaged over
#: the ``n_layer`` neighbourhood; one Gaussian layer 1.5, one uniform layer 1.06 though its Otsu
#: ratio, 3.5, is above `LAYER_RATIO`, two layers 4 σ apart 0.33). 256 neighbours, 20k points
#: at σ 0.5 % (10th / 50th / 90th percentiles): the bench's plates, where 128 neighbours saw
#: one layer, 0.48 / 0.64 / 0.82; a slab's faces with its rim's points between them (the
#: hook's 8 mm foot) 1.00 / 1.37 / 1.74; the two sides of a tube and its flanks (the mug's
#: handle, 10 mm across) 0.91 / 0.98 / 1.06: at 1.0, 100 of its points were called layered
#: and the mug's mesh lost its genus (Euler -6 against 0).
TROUGH_LIMIT = 0.9

#: A point borrowed into a layered region (near one, split along its nearest core point's
#: normal) whose own neighbourhood's Otsu ratio along that normal is below this holds one layer
#: and is not split. Ratios of 64 offsets (20k draws): one Gaussian layer 2.42 / 2.79 / 3.24
#: (5th / 50th / 95th percentiles), below 2.6 in 21 % of draws; two layers 3 σ apart with a
#: fifth of the points on the far one, 1.4 % below; 4 σ apart with a tenth, 2.4 %. Split
#: through its middle, a one-layer neighbourhood leaves the points near the cut unjoined: the
#: faces of a chair's 7 mm legs and slabs (σ 0.5 %), 23 % of the chair's points in no edge,
#: its charts' cores merged from slivers round its legs.
ONE_LAYER_RATIO = 2.6

#: The narrow two-layer test counts a neighbourhood's split only where the planes of its two
#: groups lie within this many degrees of each other (`group_planes`): two sheets, not the two
#: faces of an edge. Across an edge the split falls between the faces, or between strips of one
#: face seen along a tilted normal. The test clouds of an open box 40 × 40 × 60 mm, 8,000 points
#: at σ 0-0.2 mm (tests/test_sheet_graph.py): 39-66 % of their points were split as two layers
#: and 1,079-1,747 joined nothing; the box's meshes had 9-27 holes along its edges. The wider
#: tests ask each group's plane to lie within ``max_angle`` (35°) of the neighbourhood's; asked
#: of the 64 nearest points, that kept 15 of the 29 points the narrow test takes for two layers
#: on bench.atlas's plates at σ 0.5 % (all 29 at 45°), and the plates' gap closed in places.
LAYERS_ANGLE = 45.0
#: Fewest points of a group whose plane the two-layer tests compare: a group of one or two has
#: no plane (its normal is whatever the eigensolver returns), and without noise a split that
#: sets one point apart is many widths wide (the box at σ 0: 103 points taken for two layers).
MIN_LAYER_POINTS = 3


#: Least pooled width of a split, as a share of the neighbourhood's radius: offsets closer than
#: that are round-off, not layers. A noise-free open box (8,000 points, rotated) 1 m from the
#: origin: its flat faces' offsets, about 1e-13 mm apart, split many widths wide, and 1,461 of
#: its points were taken for two layers (298 pieces); with this floor, none.
ROUND_OFF = 1e-6


def otsu_layers(offsets: np.ndarray, floor=0.0):
    """Split each row of ``offsets`` (n, k) in two at Otsu's threshold; ``floor`` (n,) or a
    number: the least pooled width.

    Returns threshold (n,), ratio (n,) the distance of the two groups' means in pooled
    within-group widths (large when the row holds two layers), upper (n, k) bool and the pooled
    within-group width (n,)."""
    ordered = np.sort(offsets, axis=1)
    n, k = ordered.shape
    counts = np.arange(1, k)
    cumulative = np.cumsum(ordered, axis=1)[:, :-1]
    cumulative_sq = np.cumsum(ordered**2, axis=1)[:, :-1]
    total, total_sq = ordered.sum(axis=1, keepdims=True), (ordered**2).sum(axis=1, keepdims=True)
    mean_low = cumulative / counts
    mean_high = (total - cumulative) / (k - counts)
    within = (cumulative_sq - counts * mean_low**2) + (
        (total_sq - cumulative_sq) - (k - counts) * mean_high**2
    )
    between = counts * (k - counts) * (mean_high - mean_low) ** 2
    split = np.argmax(between, axis=1)
    rows = np.arange(n)
    pooled = np.maximum(np.sqrt(np.maximum(within[rows, split], 1e-300) / k), floor)
    ratio = (mean_high[rows, split] - mean_low[rows, split]) / pooled
    threshold = 0.5 * (ordered[rows, split] + ordered[rows, split + 1])
    return threshold, ratio, offsets > threshold[:, None], pooled


def group_planes(neighbourhoods: np.ndarray, upper: np.ndarray):
    """Unit normals (n, 3), (n, 3) of the planes of each (n, k, 3) neighbourhood's two groups,
    ``upper`` (n, k) and the rest, and (n,) bool whether both hold `MIN_LAYER_POINTS`."""
    _, normal_up, _, _ = plane_fits(neighbourhoods, upper.astype(float))
    _, normal_low, _, _ = plane_fits(neighbourhoods, (~upper).astype(float))
    sizes = upper.sum(axis=1)
    both_fitted = np.minimum(sizes, upper.shape[1] - sizes) >= MIN_LAYER_POINTS
    return normal_up, normal_low, both_fitted


def with_neighbours(mask: np.ndarray, near: np.ndarray) -> np.ndarray:
    """Indices of the points in ``mask`` (n,) bool and of their neighbours ``near`` (n, k)."""
    needed = np.zeros(len(mask), bool)
    needed[near[mask]] = True
    return np.flatnonzero(needed)


def trough(offsets: np.ndarray, threshold, upper, width) -> np.ndarray:
    """(n,) points of each row of ``offsets`` (n, k) within half a pooled width of its Otsu
    ``threshold``, per point within half a width of the mean of its sparser group: below 1
    where the split runs through a trough between two layers, about 1 or more across one
    layer, Gaussian or uniform (a slab's rim, whose Otsu ratio is that of two layers)."""
    half = 0.5 * width[:, None]
    at_split = np.sum(np.abs(offsets - threshold[:, None]) < half, axis=1)
    counts = []
    for group in (upper, ~upper):
        mean = np.sum(np.where(group, offsets, 0.0), axis=1) / np.maximum(group.sum(axis=1), 1)
        counts.append(np.sum(np.abs(offsets - mean[:, None]) < half, axis=1))
    return at_split / np.maximum(np.minimum(*counts), 1)


class SheetGraph(BaseEstimator):
    """kNN graph of a surface cloud with the edges between different sheets removed.

    Parameters
    ----------
    n_neighbors : K of the kNN graph whose edges are tested.
    n_layer : neighbours of the plane fit and of the two-layer test (>= n_neighbors).
    max_angle : largest angle (degrees) between two joined points' unoriented normals.
    plane_factor : how many local noise widths a neighbour may lie from a point's plane.
    layer_ratio : Otsu ratio above which a neighbourhood is two layers (`LAYER_RATIO`).
    margin : in a layered neighbourhood, within-layer widths a point must lie from the split
        between the layers to be joined (points midway between two sheets join neither).
    n_wide : wider neighbourhoods for the two-layer test (`_wide_layers`), an int or a
        sequence tried from the narrowest for the points still seen as one layer (the later
        ones with a `trough` between the layers); those of at most ``n_layer`` points: none.

    Fitted attributes: ``normals_`` (n, 3) unit, unoriented; ``noise_`` (n,) RMS distance of
    each point's own layer to its plane; ``spacing_`` (n,) mean distance to the K neighbours;
    ``planarity_`` (n,); ``layered_`` (n,) bool, neighbourhood seen as two layers;
    ``graph_`` (n, n) symmetric CSR with euclidean edge lengths; ``n_components_``,
    ``labels_`` (n,) connected piece of each point; ``kept_share_`` share of kNN edges kept.
    """

    def __init__(self, n_neighbors: int = 12, n_layer: int = 64, max_angle: float = 35.0,
                 plane_factor: float = 3.0, layer_ratio: float = LAYER_RATIO,
                 margin: float = 0.75, n_wide=(128, 256)):
        self.n_neighbors = n_neighbors
        self.n_layer = n_layer
        self.max_angle = max_angle
        self.plane_factor = plane_factor
        self.layer_ratio = layer_ratio
        self.margin = margin
        self.n_wide = n_wide

    def fit(self, points, y=None) -> SheetGraph:
        """points : (n, 3) float. Returns self."""
        points = check_points(points)
        n = len(points)
        n_layer = max(4, min(int(self.n_layer), n - 1))
        k = max(2, min(int(self.n_neighbors), n_layer))
        distances, indices = cKDTree(points).query(points, k=n_layer + 1)
        neighbourhoods = points[indices]
        _, normals, noise, planarity = plane_fits(neighbourhoods)
        layer_normals = normals.copy()
        offsets = np.einsum("nki,ni->nk", neighbourhoods - points[:, None, :], normals)
        floor = ROUND_OFF * distances[:, -1]
        threshold, ratio, upper, width = otsu_layers(offsets, floor)
        # One neighbourhood's ratio is noisy (one layer of 40 points: 2.4–3.5 in 90 % of
        # draws); layers are spatially coherent, so the ratio is averaged over the neighbourhood,
        # counting only the splits into two parallel planes (`LAYERS_ANGLE`).
        core = ratio[indices].mean(axis=1) > self.layer_ratio
        if core.any():
            at = with_neighbours(core, indices)  # the core points and those averaged with them
            normal_up, normal_low, both_fitted = group_planes(neighbourhoods[at], upper[at])
            stacked = both_fitted & (np.abs(np.einsum("ni,ni->n", normal_up, normal_low))
                                     >= np.cos(np.radians(LAYERS_ANGLE)))
            stacked_ratio = np.zeros(n)
            stacked_ratio[at] = np.where(stacked, ratio[at], 0.0)
            core &= stacked_ratio[indices].mean(axis=1) > self.layer_ratio
        seen_wide = self._wide_layers(points, n_layer, floor)
        if (seen_wide & ~core).any():
            # two layers only a wider neighbourhood sees, split along its normal where the
            # points' own neighbourhoods then hold both (averaged over the neighbourhood, as
            # above; the top of a slab thicker than a neighbourhood does not)
            across = np.einsum("nki,ni->nk", neighbourhoods - points[:, None, :],
                               self.wide_normals_)
            split = otsu_layers(across, floor)
            wide = seen_wide & ~core & (split[1] > self.layer_ratio) & (
                split[1][indices].mean(axis=1) > _WIDE_MEAN)
            layer_normals[wide] = normals[wide] = self.wide_normals_[wide]
            offsets[wide] = across[wide]
            threshold[wide], ratio[wide], upper[wide], width[wide] = (
                part[wide] for part in split)
            core |= wide
        # A point near a layered region is layered too, split along its nearest core point's
        # normal: at a sheet's border the neighbourhood is thinner along the sheet than across
        # the two layers and its own PCA normal lies in the sheet.
        near_core = core[indices]
        layered = near_core.any(axis=1)
        borrowed = layered & ~core
        if borrowed.any():
            donor = indices[borrowed, np.argmax(near_core[borrowed], axis=1)]
            layer_normals[borrowed] = layer_normals[donor]
            normals[borrowed] = layer_normals[donor]
            offsets[borrowed] = np.einsum(
                "nki,ni->nk", neighbourhoods[borrowed] - points[borrowed, None, :],
                layer_normals[borrowed])
            threshold[borrowed], ratio[borrowed], upper[borrowed], width[borrowed] = (
                otsu_layers(offsets[borrowed], floor[borrowed]))
            # Split along the donor's normal, a neighbourhood holding one layer is cut through
            # its middle, and its points near the cut joined nothing: one that clearly holds
            # one layer is left whole (`ONE_LAYER_RATIO`).
            layered &= ~(borrowed & (ratio < ONE_LAYER_RATIO))
        # A point's own layer is the side its own offset (0, column 0) fell on.
        own_upper = upper[:, 0]
        if layered.any():
            own_side = upper[layered] == own_upper[layered, None]
            _, normals_l, noise_l, planarity_l = plane_fits(
                neighbourhoods[layered], own_side.astype(float))
            normals[layered], noise[layered] = normals_l, noise_l
            planarity[layered] = planarity_l
        spacing = distances[:, 1:k + 1].mean(axis=1)
        tolerance = self.plane_factor * noise + 0.1 * spacing

        rows = np.repeat(np.arange(n), k)
        cols = indices[:, 1:k + 1].ravel()
        lengths = np.maximum(distances[:, 1:k + 1].ravel(), 1e-12 * max(spacing.max(), 1.0))
        step = points[cols] - points[rows]
        cos_angle = np.abs(np.einsum("ei,ei->e", normals[rows], normals[cols]))
        keep = cos_angle >= np.cos(np.radians(self.max_angle))
        keep &= np.abs(np.einsum("ei,ei->e", step, normals[rows])) <= tolerance[rows]
        keep &= np.abs(np.einsum("ei,ei->e", step, normals[cols])) <= tolerance[cols]
        # In a layered neighbourhood both ends must lie clearly (``margin`` within-layer widths
        # from the split) on the same layer: a point midway between two sheets joins neither.
        margin = self.margin * width
        unsure = np.abs(threshold) < margin  # the point itself (offset 0) is near the split
        for a, sign in ((rows, 1.0), (cols, -1.0)):
            across = sign * np.einsum("ei,ei->e", step, layer_normals[a])
            far = ((across > threshold[a]) != own_upper[a]) | (
                np.abs(across - threshold[a]) < margin[a])
            keep &= ~(layered[a] & (far | unsure[a]))
        graph = csr_matrix((lengths[keep], (rows[keep], cols[keep])), shape=(n, n))
        knn = csr_matrix((lengths, (rows, cols)), shape=(n, n))
        self.graph_ = graph.maximum(graph.T).tocsr()
        self.normals_ = normals
        self.noise_ = noise
        self.spacing_ = spacing
        self.planarity_ = planarity
        self.layered_ = layered
        self.n_components_, self.labels_ = connected_components(self.graph_, directed=False)
        self.kept_share_ = float(self.graph_.nnz / max(1, knn.maximum(knn.T).nnz))
        return self

    def _wide_layers(self, points: np.ndarray, n_layer: int, floor) -> np.ndarray:
        """(n,) bool: points whose ``n_wide`` nearest points hold two layers (`otsu_layers`
        averaged over the neighbourhood, as for ``n_layer``, with a `trough` between them);
        ``floor`` (n,) the least pooled width of each point's splits. Sets ``wide_normals_``
        (n, 3).

        Two sheets closer than ``n_layer`` points are wide spread their points further across
        than along: the narrow neighbourhood's PCA normal lies in the sheets and its offsets
        show one layer (sheets 3 mm apart at σ 0.74 mm, 20k points: 3 % of the points seen
        layered with 64 neighbours, 99 % with 128; edges across the gap 3600 → 228). 128
        neighbours reach only so far across: over the bench's plates their Otsu ratio, averaged,
        is 3.41 (median, seed 1) against `LAYER_RATIO` 3.4, and in patches of 100-170 points
        where it fell below, edges joined the plates (seed 1: 73 besides their rims and foot;
        one chart spanned both plates and its mesh ran between them, the gap's mid-plane open
        68 %). 256 neighbours (ratio 3.94), asked for the points 128 left as one layer though
        above one layer's ratio: every point of the plates' faces layered, no edge across
        the gap besides those of points the noise moved onto the other plate and a few at
        the foot; bench.atlas sheets seeds 0 / 1: gap open 90 / 68 % -> 98.6 / 99.4 % (the
        rest at the foot), F 0.978 / 0.960 -> 0.986 / 0.986; the other objects unchanged
        (mug: only its handle's graph changes, Chamfer 0.2379 -> 0.2378, F 0.995 -> 0.994)."""
        n = len(points)
        scales = sorted({min(int(k), n - 1) for k in np.atleast_1d(self.n_wide)})
        scales = [k for k in scales if k > n_layer]
        self.wide_normals_ = np.zeros_like(points)
        seen = np.zeros(n, bool)
        if not scales:
            return seen
        tree = cKDTree(points)
        indices = tree.query(points, k=scales[0] + 1)[1]
        near = indices[:, :n_layer + 1]
        asked = np.ones(n, bool)
        for step, k in enumerate(scales):
            if not asked.any():
                break
            at = with_neighbours(asked, near)  # the points asked and those averaged with them
            rows = indices if step == 0 else tree.query(points[at], k=k + 1)[1]
            neighbourhoods = points[rows]
            _, normals, _, _ = plane_fits(neighbourhoods)
            offsets = np.einsum("nki,ni->nk", neighbourhoods - points[at, None, :], normals)
            threshold, ratio, upper, width = otsu_layers(offsets, floor[at])
            ratios, troughs = np.zeros(n), np.zeros(n)
            # two sheets, not the two faces of an edge: each layer's own plane is parallel to
            # both
            normal_up, normal_low, both_fitted = group_planes(neighbourhoods, upper)
            cosine = np.minimum(np.abs(np.einsum("ni,ni->n", normal_up, normals)),
                                np.abs(np.einsum("ni,ni->n", normal_low, normals)))
            parallel = both_fitted & (cosine >= np.cos(np.radians(self.max_angle)))
            ratios[at] = np.where(parallel, ratio, 0.0)
            averaged = np.where(asked, ratios[near].mean(axis=1), 0.0)
            layers = averaged > self.layer_ratio
            if step:
                # wider, only with a trough between them: not one slab's faces with its rim's
                # points between them, nor a tube's two sides and its flanks
                troughs[at] = trough(offsets, threshold, upper, width)
                layers &= troughs[near].mean(axis=1) < TROUGH_LIMIT
            new = layers & ~seen
            if step == 0:  # every point's (`fit` averages its neighbours' splits along them)
                self.wide_normals_[at] = normals
            else:
                self.wide_normals_[new] = normals[np.searchsorted(at, np.flatnonzero(new))]
            seen |= new
            # a wider neighbourhood is asked where this one's ratio lies above one layer's
            # (Gaussian: 2.7 with 128 points; the plates' patches it saw as one: 3.2-3.4)
            asked = ~seen & (averaged > _WIDE_MEAN)
        return seen
