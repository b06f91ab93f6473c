"""Any cloud splits into overlapping disc-like charts (reconstruct.charts)."""

import numpy as np
import pytest

from reconstruct.charts import CONE_QUANTILE, ChartDecomposition, _most_central, oriented_normals
from reconstruct.errors import DegenerateCloudError


def torus_cloud(n=4000, major=1.0, minor=0.4, sigma=0.005, seed=0):
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 2 * np.pi, (2, 4 * n))
    # area-uniform: accept v with probability ∝ the ring's radius there
    keep = rng.uniform(0, major + minor, 4 * n) < major + minor * np.cos(v)
    u, v = u[keep][:n], v[keep][:n]
    ring = major + minor * np.cos(v)
    points = np.c_[ring * np.cos(u), ring * np.sin(u), minor * np.sin(v)]
    return points + rng.normal(0, sigma, points.shape)


@pytest.fixture(scope="module")
def torus_charts():
    points = torus_cloud()
    return points, ChartDecomposition(chart_size=1000).fit(points)


def test_cores_tile_the_cloud(torus_charts):
    points, charts = torus_charts
    joined = np.concatenate(charts.cores_)
    assert len(joined) == len(np.unique(joined))  # no point in two cores
    assert np.mean(charts.labels_ >= 0) > 0.97  # stray points the graph left alone: none
    for index, core in enumerate(charts.cores_):
        assert np.all(charts.labels_[core] == index)


def test_a_torus_needs_several_charts_each_within_its_normal_cone(torus_charts):
    points, charts = torus_charts
    assert charts.n_charts_ >= 4  # a closed surface of genus 1 is no disc
    normals = charts.graph_.normals_
    for core in charts.cores_:
        if len(core) < 2 * charts.min_points:
            continue
        oriented = oriented_normals(charts.graph_.graph_, core, normals, core[0])
        mean = oriented.mean(axis=0)
        mean /= np.linalg.norm(mean)
        # within the 70° cone of the centre point's normal (97 % of the points), so well within
        # a hemisphere about the mean normal
        assert np.quantile(oriented @ mean, 0.03) > 0.0


def test_charts_overlap_their_neighbours(torus_charts):
    points, charts = torus_charts
    ring_points = 0
    for index in range(charts.n_charts_):
        members = charts.chart(index)
        assert np.isin(charts.cores_[index], members).all()
        ring_points += len(members) - len(charts.cores_[index])
    assert ring_points > 0.2 * len(points)


def test_split_keeps_the_tiling():
    points = torus_cloud(2000)
    charts = ChartDecomposition(chart_size=800).fit(points)
    before = charts.n_charts_
    size = len(charts.cores_[0])
    new = charts.split(0)
    assert len(new) == 2 and charts.n_charts_ == before + 1
    assert sum(len(charts.cores_[i]) for i in new) == size
    assert np.all(charts.labels_[charts.cores_[new[1]]] == new[1])


def test_split_cells_are_the_split_s_and_cut_nothing():
    points = torus_cloud(2000)
    charts = ChartDecomposition(chart_size=800).fit(points)
    cores = [core.copy() for core in charts.cores_]
    cells = charts.split_cells(0)
    assert len(cells) == 2 and all(np.array_equal(a, b) for a, b in zip(cores, charts.cores_,
                                                                             strict=True))
    members = [charts.members(cell) for cell in cells]
    new = charts.split(0, cells=cells)
    for index, cell, chart in zip(new, cells, members, strict=True):
        assert np.array_equal(charts.cores_[index], cell)
        assert np.array_equal(charts.chart(index), chart)


def test_a_cloud_in_crumbs_is_refused():
    rng = np.random.default_rng(0)
    crumbs = rng.uniform(-1, 1, (40, 3))
    with pytest.raises(DegenerateCloudError):
        ChartDecomposition(min_points=50).fit(crumbs)


@pytest.fixture(scope="module")
def rod():
    import trimesh

    from sim.awkward_objects import sample_cloud

    points = sample_cloud(trimesh.creation.box((7, 7, 90)), 3000, 0.005, random_state=0)
    return points, ChartDecomposition(random_state=0).fit(points)


def test_a_thin_rod_s_cores_stay_within_their_cone_after_slivers_merge(rod):
    """The cone split leaves slivers at a rod's edges, and a sliver joins the core it shares
    most edges with, across the edge: 7 mm rods (a chair's legs) got cores wrapped round them,
    whose embeddings fold and whose meshes ran through the rods' middles."""
    _, charts = rod
    adjacency, normals = charts.graph_.graph_, charts.graph_.normals_
    for core in charts.cores_:
        if len(core) < 2 * charts.min_points:
            continue
        centre = _most_central(adjacency, core)
        oriented = oriented_normals(adjacency, core, normals, centre)
        agreement = oriented @ oriented[np.flatnonzero(core == centre)[0]]
        assert np.quantile(agreement, CONE_QUANTILE) >= np.cos(np.radians(charts.max_angle))


def test_the_slivers_left_are_those_no_neighbour_takes_within_the_cone(rod):
    """A core the second cone split leaves under 1/25 of chart_size (a 7 mm rod: 16 of 26)
    joins a neighbour where the two stay within the cone (37 cores, 31 under it, before)."""
    points, charts = rod
    again = charts._merged_small(charts.cores_, len(points), cone=True)
    assert len(again) == len(charts.cores_)
