"""The neighbourhood graph never bridges two sheets (reconstruct.sheet_graph)."""

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from reconstruct.errors import InvalidInputError, ReconstructionWarning
from reconstruct.sheet_graph import TROUGH_LIMIT, SheetGraph, otsu_layers, trough


def two_sheets(n, gap, sigma, seed=0):
    """Two parallel unit squares ``gap`` apart (shares of the diagonal), noise σ × diagonal."""
    rng = np.random.default_rng(seed)
    side = rng.integers(0, 2, n)
    diagonal = np.sqrt(2.0)
    points = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), (side - 0.5) * gap * diagonal]
    return points + rng.normal(0, sigma * diagonal, (n, 3)), side


def curled_sheet(n, turn_deg=300, radius=0.3, sigma=0.005, seed=0):
    """A sheet rolled ``turn_deg`` about z: its two ends face each other across a small gap."""
    rng = np.random.default_rng(seed)
    phi = rng.uniform(0, np.radians(turn_deg), n)
    r = radius * (1 - 0.08 * phi)  # a spiral: the overlapping ends lie 0.08·2π·r apart
    points = np.c_[r * np.cos(phi), r * np.sin(phi), rng.uniform(0, 1, n)]
    return points + rng.normal(0, sigma, (n, 3)), phi


def sheet_purity(graph, side):
    """Share of the points in the two largest pieces that lie on their piece's majority sheet,
    and the share of all points in those two pieces."""
    _, labels = connected_components(graph, directed=False)
    largest = np.argsort(np.bincount(labels))[-2:]
    inside = np.isin(labels, largest)
    majority = sum(np.bincount(side[labels == piece]).max() for piece in largest)
    return majority / inside.sum(), inside.mean()


def cross_share(graph, side):
    coo = graph.tocoo()
    return float(np.mean(side[coo.row] != side[coo.col]))


def test_otsu_finds_two_layers_and_not_one():
    rng = np.random.default_rng(0)
    one = rng.normal(size=(2000, 64))
    two = one + 5 * rng.integers(0, 2, (2000, 64))
    assert np.median(otsu_layers(one)[1]) < 3.0 < 4.5 < np.median(otsu_layers(two)[1])


def test_a_trough_tells_two_layers_from_one_thick_one():
    # A uniform layer (a slab's rim between its faces) has the Otsu ratio of two layers 4 σ
    # apart (3.5 against 4.2: `LAYER_RATIO` 3.4 lies between); only two layers leave a trough.
    rng = np.random.default_rng(0)
    one = rng.normal(size=(2000, 256))
    uniform = rng.uniform(-2, 2, (2000, 256))
    two = rng.normal(size=(2000, 256)) + 4 * rng.integers(0, 2, (2000, 256))

    def median_trough(offsets):
        threshold, _, upper, width = otsu_layers(offsets)
        return np.median(trough(offsets, threshold, upper, width))

    assert np.median(otsu_layers(uniform)[1]) > 3.4
    assert median_trough(two) < 0.5 < TROUGH_LIMIT < median_trough(uniform) < median_trough(one)


def test_sheets_two_percent_apart_at_half_percent_noise_stay_apart():
    points, side = two_sheets(4000, gap=0.02, sigma=0.005)
    graph = SheetGraph().fit(points)
    assert graph.layered_.mean() > 0.9
    # Gaussian noise of 0.5 % moves 2.3 % of the points nearer the other sheet than their own:
    # those join the other sheet; no edge may bridge the two pieces.
    assert cross_share(graph.graph_, side) < 0.05
    purity, covered = sheet_purity(graph.graph_, side)
    assert purity > 0.96 and covered > 0.85


def test_sheets_at_one_percent_noise_when_four_sigma_apart_with_a_wide_layer_test():
    # At σ 1 % the layer test needs neighbourhoods wider than the noise (256 points here); a
    # few edges at the open squares' borders still cross (measured 0.6 %), so each sheet's own
    # graph is checked, not the separation of the pieces.
    points, side = two_sheets(12000, gap=0.04, sigma=0.01)
    graph = SheetGraph(n_layer=256).fit(points)
    assert graph.layered_.mean() > 0.95
    assert cross_share(graph.graph_, side) < 0.01
    for sheet in (0, 1):
        own = graph.graph_[side == sheet][:, side == sheet]
        sizes = np.bincount(connected_components(own, directed=False)[1])
        assert sizes.max() > 0.8 * sizes.sum()


def test_one_sheet_stays_one_piece():
    points, _ = two_sheets(3000, gap=0.0, sigma=0.01)
    graph = SheetGraph().fit(points)
    assert graph.layered_.mean() < 0.05
    sizes = np.bincount(graph.labels_)
    assert sizes.max() > 0.99 * len(points)


@pytest.mark.parametrize("apart", [1e-9, 0.02, 0.1])  # of the nearest-neighbour spacing
def test_a_sheet_merged_with_its_copy_is_one_sheet(apart):
    # (a cloud saved twice, its copy moved by round-off or a re-registration): kept twice,
    # 13-16 % of the points were called layered and the sheet fell into 157-222 pieces
    points, _ = two_sheets(3000, gap=0.0, sigma=0.01)
    spacing = np.median(cKDTree(points).query(points, 2)[0][:, 1])
    copy = points + np.random.default_rng(5).normal(0, apart * spacing, points.shape)
    with pytest.warns(ReconstructionWarning, match="merged"):
        graph = SheetGraph().fit(np.vstack([points, copy]))
    assert graph.n_components_ == 1 and not graph.layered_.any()


def test_a_curled_sheet_keeps_its_overlapping_ends_apart():
    points, phi = curled_sheet(6000)
    graph = SheetGraph().fit(points).graph_
    coo = graph.tocoo()
    # an edge joins points at nearly the same angle along the sheet, never its two ends
    assert np.abs(phi[coo.row] - phi[coo.col]).max() < 1.0
    sizes = np.bincount(connected_components(graph, directed=False)[1])
    assert sizes.max() > 0.97 * len(points)


def test_bad_points_are_refused():
    with pytest.raises(InvalidInputError):
        SheetGraph().fit(np.array([[0.0, 0.0, np.nan]] * 10))


def test_plates_farther_apart_than_a_neighbourhood_is_wide_stay_apart():
    # The bench's two 1.5 mm plates 3 mm apart, 20k points at σ 0.5 %: 64 neighbours reach
    # less far along the plates than across both, so their PCA normal lies in the plates and
    # only a wider neighbourhood (`n_wide`) sees two layers.
    from sim.awkward_objects import sample_cloud, sheets

    points = sample_cloud(sheets(), 20000, 0.005, random_state=0)
    plate = np.where(points[:, 2] > 15, np.sign(points[:, 0]), 0)  # 0: the foot

    def crossing(graph):
        coo = graph.graph_.tocoo()
        return float(np.mean(plate[coo.row] * plate[coo.col] < 0))

    narrow = SheetGraph(n_wide=0).fit(points)
    wide = SheetGraph().fit(points)
    assert narrow.layered_[plate != 0].mean() < 0.1 and crossing(narrow) > 0.01
    assert wide.layered_[plate != 0].mean() > 0.8 and crossing(wide) < 0.005
    sizes = np.bincount(wide.labels_)
    assert sizes.max() > 0.7 * len(points)  # the plates stay joined through their foot


def test_the_plates_stay_apart_where_128_neighbours_see_one_layer():
    # Seed 1 of the bench's plates: in patches of 100-170 points the Otsu ratio of 128
    # neighbours, averaged, fell below `LAYER_RATIO` (median 3.41 over the plates), and the
    # plates' faces were joined there, so one chart spanned both plates and its mesh ran
    # between them (gap's mid-plane open 68 %). 256 neighbours see the two layers everywhere.
    import trimesh

    from sim.awkward_objects import sample_cloud, sheets

    mesh = sheets()
    rng = np.random.default_rng(1)  # `sample_cloud`'s draws, with the points' faces
    clean, _ = trimesh.sample.sample_surface(mesh, 20000, seed=rng.integers(2**31))
    points = clean + rng.normal(0, 0.005 * np.linalg.norm(mesh.extents), clean.shape)
    assert np.allclose(points, sample_cloud(mesh, 20000, 0.005, random_state=1))
    inner = (clean[:, 2] > 15) & (clean[:, 2] < 100) & (np.abs(clean[:, 1]) < 45)
    plate = (clean[inner, 0] > 0).astype(int)
    graph = SheetGraph().fit(points)
    # (points whose own 64 neighbours hold one plate are left whole: `ONE_LAYER_RATIO`)
    assert graph.layered_[inner].mean() > 0.9
    # the plates' faces, without their rims and foot: each of the two largest pieces is one
    # plate (points the noise moved onto the other plate join it; measured 0.9996, 128
    # neighbours only: 0.51, one piece holding both plates)
    purity, covered = sheet_purity(graph.graph_[inner][:, inner], plate)
    assert purity > 0.99 and covered > 0.6


def test_a_slab_s_faces_stay_joined_where_a_neighbourhood_holds_one_layer():
    # An 80 mm slab 6 mm (10 noise widths) thick: 128 neighbours see its two faces, 64 only
    # near its rim. A face point borrowed into the layered region, split along its donor's
    # normal, had its one layer cut through the middle and the points near the cut joined
    # nothing: 32 % of the faces' inner points (27 % with `ONE_LAYER_RATIO`; the rest lie
    # within reach of the rim, where 64 neighbours hold both faces).
    import trimesh

    slab = trimesh.creation.box((80, 80, 6.0))
    rng = np.random.default_rng(0)
    clean, _ = trimesh.sample.sample_surface(slab, 16000, seed=rng.integers(2**31))
    points = clean + rng.normal(0, 0.005 * np.linalg.norm(slab.extents), clean.shape)
    graph = SheetGraph().fit(points)
    inner = (np.abs(clean[:, :2]).max(axis=1) < 30) & (np.abs(clean[:, 2]) > 2.99)
    joined = np.diff(graph.graph_.indptr) > 0
    assert joined[inner].mean() > 0.70
    faces = np.abs(clean[:, 2]) > 2.99  # not the rim, which joins the faces
    side = (clean[faces, 2] > 0).astype(int)
    assert cross_share(graph.graph_[faces][:, faces], side) == 0  # the faces stay apart


def open_box(rng):
    """(8000, 3) points on a 40 x 40 x 60 mm box without its bottom face, drawn with ``rng``."""
    import trimesh

    box = trimesh.creation.box((40, 40, 60))
    box = trimesh.Trimesh(box.vertices, box.faces[~np.isclose(box.triangles_center[:, 2], -30)])
    return trimesh.sample.sample_surface(box, 8000, seed=rng.integers(2**31))[0]


@pytest.mark.parametrize("sigma", [0.0, 0.1, 0.2])
def test_the_faces_of_an_edge_are_one_sheet(sigma):
    # An open box 40 x 40 x 60 mm, 8,000 points (1.2 mm apart): a neighbourhood across an edge
    # splits into its two faces, into strips of one face seen along a tilted normal, or (without
    # noise) sets one point of the other face apart, each many widths wide. Taken for two
    # layers, 39-66 % of these clouds' points were split and 1,079-1,747 joined nothing (the
    # box's mesh had 9-27 holes along its edges). Now none here; the narrow or the wide test
    # still takes a corner or an edge for two layers now and then (seeds 0-19 at σ 0-0.3 mm:
    # at most 2.5 % of the points, the largest piece 98.8 % of them).
    rng = np.random.default_rng(0)
    clean = open_box(rng)
    graph = SheetGraph().fit(clean + rng.normal(0, sigma, clean.shape))
    assert graph.layered_.mean() < 0.05
    assert np.bincount(graph.labels_).max() > 0.97 * len(clean)


def test_round_off_is_not_a_layer():
    # A noise-free cloud far from the origin: its flat faces' offsets, ~1e-13 apart, are
    # round-off, and every split of them was many widths wide (`ROUND_OFF`): 1,461 of this box's
    # points were taken for two layers, in 298 pieces.
    clean = open_box(np.random.default_rng(0))
    rotation, _ = np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))
    graph = SheetGraph().fit(clean @ rotation.T + 1000.0)
    assert graph.layered_.mean() < 0.05
    assert np.bincount(graph.labels_).max() > 0.97 * len(clean)
