"""Known answers of the boundary interpolant samplers (reconstruct.boundary)."""

import numpy as np
import pytest
import shapely

from reconstruct.boundary import MultiDepthBoundary, PCABoundary, boundary_geometry
from reconstruct.errors import DegenerateCloudError, InvalidInputError


def noisy_disc(m, radius=2.0, sigma=0.04, seed=0):
    """(m, 2) uniform in a disc of ``radius`` plus Gaussian noise ``sigma`` per coordinate."""
    rng = np.random.default_rng(seed)
    r = radius * np.sqrt(rng.uniform(0, 1, m))
    t = rng.uniform(0, 2 * np.pi, m)
    return np.column_stack([r * np.cos(t), r * np.sin(t)]) + rng.normal(0, sigma, (m, 2))


def noisy_region(region, m, sigma, seed=0):
    """(m, 2) uniform inside a shapely polygon plus Gaussian noise ``sigma``."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array(region.bounds[:2]), np.array(region.bounds[2:])
    points = rng.uniform(lo, hi, (4 * m, 2))
    points = points[shapely.contains_xy(region, points[:, 0], points[:, 1])][:m]
    assert len(points) == m
    return points + rng.normal(0, sigma, points.shape)


def winding(points, centre):
    """Total signed turning of the loop's direction from ``centre``, in turns."""
    angle = np.arctan2(*(points - centre).T[::-1])
    step = np.diff(np.append(angle, angle[0]))
    return np.sum((step + np.pi) % (2 * np.pi) - np.pi) / (2 * np.pi)


@pytest.mark.parametrize("depth", [1, 2, 3, 4])
def test_noisy_disc_interpolants_ring_the_rim(depth):
    radius = 2.0
    uv = noisy_disc(5000, radius, sigma=0.02 * radius, seed=0)
    model = MultiDepthBoundary(depth=depth).fit(uv)

    assert len(model.depth_paths_) == depth
    np.testing.assert_array_equal(model.points_, uv[model.indices_])
    # Every point of the first loop, and those of the deeper loops that run beside it.
    assert set(model.depth_paths_[0]) <= set(model.indices_) <= set(
        np.concatenate(model.depth_paths_)
    )
    assert len(np.unique(model.indices_)) == len(model.indices_), "depths are disjoint"
    r = np.hypot(*(model.points_ - model.centroid_).T) / radius
    assert abs(r.mean() - 1) < 0.035
    assert r.min() > 0.85 and r.max() < 1.08
    # One consistent counter-clockwise loop around the centroid, mostly monotone in angle.
    assert winding(model.points_, model.centroid_) == pytest.approx(1.0, abs=1e-9)
    for path in model.depth_paths_:
        assert winding(uv[path], model.centroid_) == pytest.approx(1.0, abs=1e-9)
    # Deeper loops lie further in.
    mean_r = [np.hypot(*(uv[p] - model.centroid_).T).mean() for p in model.depth_paths_]
    assert np.all(np.diff(mean_r) < 0)


def test_corners_are_the_furthest_inlier_of_each_sector():
    uv = noisy_disc(3000, seed=1)
    model = MultiDepthBoundary(depth=1, n_corners=12).fit(uv)
    offset = uv - model.centroid_
    radius = np.hypot(*offset.T)
    sector = np.floor((np.arctan2(offset[:, 1], offset[:, 0]) + np.pi) / (2 * np.pi) * 12)
    expected = [
        np.flatnonzero(sector == s)[np.argmax(radius[sector == s])]
        for s in range(12)
        if (sector == s).any()
    ]
    assert len(model.corners_) == 12
    assert sorted(model.corner_indices_[0]) == sorted(expected)
    np.testing.assert_array_equal(model.corners_, uv[model.corner_indices_[0]])


def test_far_outliers_never_move_the_boundary():
    radius = 2.0
    uv = noisy_disc(3000, radius, sigma=0.02, seed=2)
    far = np.array([[5 * radius, 0.0], [0.0, -3 * radius], [2 * radius, 2 * radius]])
    clean = MultiDepthBoundary().fit(uv)
    model = MultiDepthBoundary().fit(np.vstack([uv, far]))

    assert model.outliers_[-3:].all()
    assert not np.isin(model.indices_, np.arange(3000, 3003)).any()
    assert np.hypot(*model.points_.T).max() < 1.06 * radius
    # The same interpolants as without the outliers, up to the centroid's tiny shift.
    assert len(np.intersect1d(model.indices_, clean.indices_)) > 0.8 * len(clean.indices_)

    # The Yumer-Kara baseline has no outlier test: the far point is a PCA corner on its loop.
    baseline = PCABoundary().fit(np.vstack([uv, far]))
    assert 3000 in baseline.indices_
    assert np.hypot(*baseline.points_.T).max() > 4.9 * radius


def test_outer_band_does_not_change_the_result():
    uv = noisy_region(shapely.box(-1, -1, 1, 1), 10000, sigma=0.01, seed=3)
    banded = MultiDepthBoundary(depth=3).fit(uv)
    full = MultiDepthBoundary(depth=3, band_factor=None).fit(uv)
    np.testing.assert_array_equal(banded.indices_, full.indices_)


def test_independent_of_scale_and_position_and_deterministic():
    uv = noisy_disc(2000, seed=4)
    a = MultiDepthBoundary().fit(uv)
    b = MultiDepthBoundary().fit(uv * 1000.0 + [3e4, -7e3])
    c = MultiDepthBoundary().fit(uv)
    np.testing.assert_array_equal(a.indices_, b.indices_)
    np.testing.assert_array_equal(a.indices_, c.indices_)


def test_empty_sectors_and_disconnected_wedges_fall_back():
    # A C-shape seen from its centroid in the hole: the mouth empties two of 16 sectors.
    ring = shapely.Point(0, 0).buffer(1, 64).difference(shapely.Point(0, 0).buffer(0.5, 64))
    c_shape = ring.difference(shapely.box(0, -0.6, 2, 0.6))
    uv = noisy_region(c_shape, 3000, sigma=0.005, seed=5)
    model = MultiDepthBoundary(n_corners=16).fit(uv)
    assert len(model.corners_) == 14
    assert winding(model.points_, model.centroid_) == pytest.approx(1.0, abs=1e-9)

    # Two separate blobs: wedges spanning the gap have no connected graph.
    blobs = np.vstack(
        [noisy_disc(800, 1.0, 0.01, 6) - [3, 0], noisy_disc(800, 1.0, 0.01, 7) + [3, 0]]
    )
    model = MultiDepthBoundary(depth=2).fit(blobs)
    assert (model.points_[:, 0] < -2).any() and (model.points_[:, 0] > 2).any()
    assert winding(model.points_, model.centroid_) == pytest.approx(1.0, abs=1e-9)


def test_pca_baseline_corners_and_outer_loop():
    # An ellipse with semi-axes 3 and 1 turned by 30°: its PCA extremes are the axis ends.
    turn = np.deg2rad(30)
    rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    unit = noisy_disc(4000, 1.0, sigma=0.0, seed=8)
    uv = (unit * [3.0, 1.0]) @ rotation.T
    model = PCABoundary().fit(uv)

    corners = np.abs(model.corners_ @ rotation)  # in the ellipse's own axes
    corners = corners[np.argsort(-corners[:, 0])]
    assert len(corners) == 4
    assert (corners[:2, 0] > 2.97).all() and (corners[2:, 1] > 0.98).all()
    # The loop runs along the outermost points (spacing about 0.05: the outermost of a uniform
    # sample lie about 0.03 inside on average).
    t = np.linspace(0, 2 * np.pi, 2000)
    rim = shapely.LinearRing((np.column_stack([3 * np.cos(t), np.sin(t)])) @ rotation.T)
    gap = shapely.distance(rim, shapely.points(model.points_))
    assert np.median(gap) < 0.04 and np.percentile(gap, 90) < 0.1 and gap.max() < 0.2
    assert winding(model.points_, model.centroid_) == pytest.approx(1.0, abs=1e-9)
    assert model.depth_paths_[0] is model.indices_


def test_bad_input():
    with pytest.raises(InvalidInputError, match="NaN"):
        MultiDepthBoundary().fit(np.full((50, 2), np.nan))
    with pytest.raises(InvalidInputError, match=r"shape \(m, 2\)"):
        MultiDepthBoundary().fit(np.zeros((50, 3)))
    with pytest.raises(InvalidInputError, match="5 embedded points"):
        PCABoundary().fit(np.random.default_rng(0).normal(size=(5, 2)))
    with pytest.raises(DegenerateCloudError, match="sectors"):
        MultiDepthBoundary().fit(np.outer(np.linspace(-1, 1, 200), [1.0, 2.0]))
    uv = noisy_disc(200)
    for params in (
        {"depth": 0},
        {"n_corners": 4},
        {"c1": 0.0},
        {"c2": -1.0},
        {"n_neighbors": 1},
        {"density_factor": 0.5},
        {"band_factor": 0.0},
    ):
        with pytest.raises(InvalidInputError, match=next(iter(params))):
            MultiDepthBoundary(**params).fit(uv)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_outer_loop_follows_the_long_sides_of_an_elongated_region(seed):
    # Rays from the centroid meet the long sides of a 4.7:1 rectangle (the S-curve's embedding)
    # at grazing angles; depth below the envelope is measured across its edges, not along the
    # rays, so the loop keeps to the sides instead of cutting in (radially: 0.889–0.912).
    rng = np.random.default_rng(seed)
    uv = rng.uniform(size=(1600, 2)) * [4.7, 1.0]
    spacing = np.sqrt(4.7 / 1600)
    rect = shapely.box(0.0, 0.0, 4.7, 1.0)
    loop = MultiDepthBoundary(depth=1).fit(uv).depth_paths_[0]
    assert shapely.Polygon(uv[loop]).area > 0.915 * rect.area
    assert shapely.distance(rect.exterior, shapely.points(uv[loop])).max() < 3 * spacing


def test_paths_bridge_gaps_between_outer_points_that_knn_misses():
    """Outer points 2.5 grid spacings apart, above a dense grid: each one's 8 nearest
    neighbours are grid points, so the kNN graph alone detours inwards; the short Delaunay
    edges along the outside keep the path on the outer row."""
    from reconstruct.boundary import _dijkstra_path

    gx, gy = np.meshgrid(np.arange(0, 2.01, 0.1), np.arange(-1.0, 0.001, 0.1))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    row = np.column_stack([np.arange(0, 2.01, 0.25), np.full(9, 0.05)])
    points = np.vstack([row[:1], row[1:-1], grid, row[-1:]])
    inward = np.concatenate([np.zeros(8), 0.05 - grid[:, 1], [0.0]])
    with_delaunay = _dijkstra_path(points, inward, 1.0, 1.0, 8, reach=0.3)
    assert list(with_delaunay) == [0, *range(1, 8), len(points) - 1]
    knn_only = _dijkstra_path(points, inward, 1.0, 1.0, 8, reach=0.0)
    assert np.any((knn_only > 7) & (knn_only < len(points) - 1))  # through the grid


def test_a_deeper_point_far_inside_the_first_loop_is_no_interpolant():
    from reconstruct.boundary import _order_along_first

    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    outer, inner = np.column_stack([np.cos(t), np.sin(t)]), 0.95 * np.column_stack(
        [np.cos(t + 0.05), np.sin(t + 0.05)]
    )
    inner[10] *= 0.5  # a detour through the interior
    uv = np.vstack([outer, inner])
    order = _order_along_first(uv, [np.arange(40), np.arange(40, 80)], max_inset=0.1)
    assert 50 not in order and len(order) == 79
    assert set(range(40)) <= set(order)
    with pytest.raises(InvalidInputError, match="max_inset"):
        MultiDepthBoundary(max_inset=0).fit(uv)


def test_the_geometry_kept_between_depths_gives_the_same_paths():
    uv = np.vstack([noisy_disc(3000, seed=3), [[9.0, 9.0]]])  # with a far outlier
    geometry = boundary_geometry(uv)
    assert geometry.outliers[-1] and geometry.outliers.sum() >= 1
    for depth in (1, 2, 3):
        fresh = MultiDepthBoundary(depth=depth).fit(uv)
        kept = MultiDepthBoundary(depth=depth).fit(uv, geometry)
        np.testing.assert_array_equal(kept.indices_, fresh.indices_)
        np.testing.assert_array_equal(kept.outliers_, fresh.outliers_)
