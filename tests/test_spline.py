"""Known answers of the closed boundary spline (reconstruct.spline) and of the whole boundary
step (interpolants + spline) against ground-truth regions."""

import warnings

import numpy as np
import pytest
import shapely
from scipy.interpolate import splev

from reconstruct.boundary import MultiDepthBoundary, PCABoundary
from reconstruct.errors import FitError, InvalidInputError, NotFittedError, ReconstructionWarning
from reconstruct.meshing import signed_area
from reconstruct.spline import BoundarySpline, _largest_loop

SQUARE = shapely.box(-1, -1, 1, 1)
L_SHAPE = shapely.Polygon([(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)])


def circle(n, radius=3.0, start=0.0):
    t = start + np.linspace(0, 2 * np.pi, n, endpoint=False)
    return radius * np.column_stack([np.cos(t), np.sin(t)])


def noisy_disc(m, radius=2.0, sigma=0.04, seed=0):
    rng = np.random.default_rng(seed)
    r = radius * np.sqrt(rng.uniform(0, 1, m))
    t = rng.uniform(0, 2 * np.pi, m)
    return np.column_stack([r * np.cos(t), r * np.sin(t)]) + rng.normal(0, sigma, (m, 2))


def noisy_region(region, m, sigma, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = np.array(region.bounds[:2]), np.array(region.bounds[2:])
    points = rng.uniform(lo, hi, (4 * m, 2))
    points = points[shapely.contains_xy(region, points[:, 0], points[:, 1])][:m]
    return points + rng.normal(0, sigma, points.shape)


def turning(polygon):
    """Total absolute turning of a closed polygon, radians (2π for a convex loop)."""
    seg = np.diff(polygon, axis=0)
    heading = np.arctan2(seg[:, 1], seg[:, 0])
    step = np.diff(np.append(heading, heading[0]))
    return np.abs((step + np.pi) % (2 * np.pi) - np.pi).sum()


def fit_quietly(points, **params):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReconstructionWarning)
        return BoundarySpline(**params).fit(points)


def test_interpolates_a_circle_and_is_closed_and_smooth_at_the_seam():
    points = circle(40, radius=3.0, start=0.3)
    spline = BoundarySpline(lam=0.0).fit(points)
    # λ = 0 interpolates: the spline goes through every interpolant.
    at_points = np.column_stack(splev(spline.u_[:-1], spline.tck_))
    np.testing.assert_allclose(at_points, points, atol=1e-9)
    assert spline.residual_ < 1e-9
    radius = np.hypot(*spline.polygon_.T)
    np.testing.assert_allclose(radius, 3.0, rtol=2e-4)
    # Closed: the polygon repeats its first point; value and derivatives agree at the seam.
    np.testing.assert_array_equal(spline.polygon_[0], spline.polygon_[-1])
    assert len(spline.polygon_) == max(64, 4 * 40) + 1
    for der in (0, 1, 2):
        np.testing.assert_allclose(
            splev(0.0, spline.tck_, der=der), splev(1.0, spline.tck_, der=der), atol=1e-9
        )
    assert spline.is_simple_
    assert spline.length_ == pytest.approx(2 * np.pi * 3.0, rel=1e-4)


def test_smoothing_follows_the_scaled_variance_rule_and_is_scale_free():
    rng = np.random.default_rng(0)
    points = circle(200, radius=2.0) + rng.normal(0, 0.02, (200, 2))
    spline = BoundarySpline(lam=0.003).fit(points)
    variance = np.sum((points - points.mean(axis=0)) ** 2) / 200
    assert spline.smoothing_ == pytest.approx(0.003 * 200 * variance, rel=1e-12)
    # λ is the mean squared residual allowed, as a fraction of the variance: FITPACK uses it all.
    assert spline.residual_**2 == pytest.approx(0.003 * variance, rel=1e-3)

    scaled = BoundarySpline(lam=0.003).fit(points * 1000.0 + [5e4, -2e4])
    np.testing.assert_allclose(scaled.polygon_, spline.polygon_ * 1000.0 + [5e4, -2e4], rtol=1e-6)
    assert scaled.n_knots_ == spline.n_knots_

    # "local" measures jaggedness: about the noise variance (0.02² per coordinate, normal part).
    local = BoundarySpline(lam=1.0, variance="local").fit(points)
    assert local.smoothing_ / 200 == pytest.approx(0.02**2, rel=0.3)


@pytest.mark.parametrize(
    "variance, lams", [("global", (1e-4, 3e-4, 1e-3)), ("local", (0.25, 0.5, 1.0))]
)
def test_larger_lambda_is_smoother_smaller_lambda_tracks_closer(variance, lams):
    interpolants = MultiDepthBoundary(depth=3).fit(noisy_disc(3000, seed=0)).points_
    fits = [fit_quietly(interpolants, lam=lam, variance=variance) for lam in lams]
    raw = [np.vstack([f.evaluate(4 * len(interpolants)), f.evaluate(1)]) for f in fits]
    bends = [turning(p) for p in raw]
    hull_ratio = [
        shapely.LineString(p).length / shapely.MultiPoint(p).convex_hull.length for p in raw
    ]
    assert bends[0] > bends[1] > bends[2] >= 2 * np.pi - 1e-9
    assert hull_ratio[0] > hull_ratio[1] > hull_ratio[2] >= 1.0 - 1e-9
    assert fits[0].n_knots_ > fits[1].n_knots_ > fits[2].n_knots_
    assert fits[0].residual_ < fits[1].residual_ < fits[2].residual_


@pytest.mark.parametrize("depth", [1, 2, 3, 4])
@pytest.mark.parametrize("params", [{}, {"lam": 2.0, "variance": "local"}], ids=["paper", "local"])
def test_noisy_disc_gives_a_round_boundary_at_every_depth(depth, params):
    radius = 2.0
    interpolants = MultiDepthBoundary(depth=depth).fit(noisy_disc(5000, radius, 0.04)).points_
    spline = BoundarySpline(**params).fit(interpolants)
    r = np.hypot(*spline.polygon_.T) / radius
    # The paper's λ = 0.002 spends its residual budget shrinking the loop by up to √λ ≈ 4.5 %.
    assert abs(r.mean() - 1) < (0.035 if params else 0.05)
    assert np.abs(r - 1).max() < (0.06 if params else 0.08)
    assert spline.is_simple_


@pytest.mark.parametrize("region", [SQUARE, L_SHAPE], ids=["square", "L"])
@pytest.mark.parametrize("depth, tolerance", [(1, 0.025), (3, 0.05)])
def test_square_and_l_shape_areas(region, depth, tolerance):
    m = 12000
    uv = noisy_region(region, m, sigma=np.sqrt(region.area / m), seed=0)
    interpolants = MultiDepthBoundary(depth=depth).fit(uv).points_
    for params in ({}, {"lam": 2.0, "variance": "local"}):
        spline = BoundarySpline(**params).fit(interpolants)
        polygon = shapely.Polygon(spline.polygon_)
        assert polygon.area == pytest.approx(region.area, rel=tolerance)
        # The paper's λ also rounds the corners off: the local rule keeps them sharper.
        assert polygon.symmetric_difference(region).area < (0.05 if params else 0.1) * region.area


def test_multidepth_beats_the_pca_baseline_on_noisy_data():
    m = 5000
    uv = noisy_region(SQUARE, m, sigma=3 * np.sqrt(SQUARE.area / m), seed=1)
    ours = shapely.Polygon(BoundarySpline().fit(MultiDepthBoundary().fit(uv).points_).polygon_)
    theirs = shapely.Polygon(BoundarySpline().fit(PCABoundary().fit(uv).points_).polygon_)
    # seeds 1–3 measured 0.52–0.58 (area), 0.55–0.62 (symmetric difference), 0.58–0.75 (Hausdorff)
    for error, ratio in (
        (lambda p: abs(p.area - SQUARE.area), 0.7),
        (lambda p: p.symmetric_difference(SQUARE).area, 0.7),
        (lambda p: p.hausdorff_distance(SQUARE), 0.85),
    ):
        assert error(ours) < ratio * error(theirs)


def test_sample_by_spacing_and_contains():
    spline = BoundarySpline(lam=0.0).fit(circle(64, radius=2.0))
    samples = spline.sample_by_spacing(0.1)
    assert len(samples) == round(spline.length_ / 0.1)
    np.testing.assert_array_equal(samples[0], spline.polygon_[0])
    gaps = np.hypot(*np.diff(np.vstack([samples, samples[:1]]), axis=0).T)
    np.testing.assert_allclose(gaps, 0.1, rtol=0.01)
    on_polygon = shapely.distance(shapely.LinearRing(spline.polygon_), shapely.points(samples))
    assert on_polygon.max() < 1e-9

    probe = np.vstack([circle(50, radius=1.8), circle(50, radius=2.2), [[0.0, 0.0]]])
    inside = spline.contains(probe)
    assert inside.dtype == bool and inside.shape == (101,)
    np.testing.assert_array_equal(inside, np.r_[np.ones(50), np.zeros(50), 1].astype(bool))


def test_self_crossing_spline_is_repaired_to_its_largest_loop():
    points = circle(60, radius=1.0)
    points[[20, 21]] = points[[21, 20]]  # a twist: the interpolating spline crosses itself
    with pytest.warns(ReconstructionWarning, match="crosses itself"):
        spline = BoundarySpline(lam=0.0).fit(points)
    assert not spline.is_simple_
    repaired = shapely.Polygon(spline.polygon_)
    assert repaired.is_valid and shapely.LinearRing(spline.polygon_).is_simple
    assert repaired.area == pytest.approx(np.pi, rel=0.03)
    np.testing.assert_array_equal(spline.polygon_[0], spline.polygon_[-1])


def test_interpolants_that_outline_no_one_region_are_refused():
    # a depth deeper than the cloud is wide takes most of its points as interpolants, in an
    # order that crosses its inside back and forth: no loop of the spline is the region
    rng = np.random.default_rng(0)
    radius, angle = np.sqrt(rng.uniform(size=300)), rng.uniform(0, 2 * np.pi, 300)
    order = np.argsort(angle + 0.3 * rng.normal(size=300))  # roughly round, but every which way
    wandering = np.c_[radius * np.cos(angle), radius * np.sin(angle)][order]
    with pytest.raises(FitError, match="crosses itself all over.*smaller --depth"):
        BoundarySpline(lam=1.0, variance="local").fit(wandering)


def test_largest_loop_is_make_valids_largest_piece_from_the_spline_start():
    t = np.linspace(0.0, 2 * np.pi, 400)
    x = np.sin(t) * np.where(np.sin(t) > 0, 1.5, 1.0)
    figure = np.column_stack([x, np.sin(2 * t) / 2])  # an 8: lobes of unequal size
    figure[-1] = figure[0]
    loop, share = _largest_loop(figure)
    pieces = shapely.get_parts(shapely.make_valid(shapely.Polygon(figure)))
    largest = max(pieces, key=lambda piece: piece.area)
    assert share == pytest.approx(largest.area / sum(piece.area for piece in pieces), rel=1e-9)
    assert share == pytest.approx(0.6, abs=1e-3)  # lobes of areas 1.5 : 1
    assert shapely.Polygon(loop).area == pytest.approx(largest.area, rel=1e-12)
    assert {tuple(v) for v in loop} == {tuple(v) for v in np.asarray(largest.exterior.coords)}
    np.testing.assert_array_equal(loop[0], loop[-1])
    assert np.sign(signed_area(loop)) == np.sign(signed_area(figure))
    from_start = np.linalg.norm(loop - figure[0], axis=1)
    assert from_start[0] == from_start.min() < 0.01  # it starts at the crossing, where 8 does


def test_input_is_left_alone_and_duplicates_are_dropped():
    points = circle(30, radius=1.5)
    original = points.copy()
    spline = BoundarySpline(lam=1e-3).fit(points)
    np.testing.assert_array_equal(points, original)
    doubled = np.repeat(points, 2, axis=0)  # every point twice in a row, and last == first
    again = BoundarySpline(lam=1e-3).fit(np.vstack([doubled, doubled[:1]]))
    np.testing.assert_allclose(again.polygon_, spline.polygon_, atol=1e-12)
    repeat = BoundarySpline(lam=1e-3).fit(points)
    np.testing.assert_array_equal(repeat.polygon_, spline.polygon_)


def test_bad_input_and_bad_parameters():
    with pytest.raises(InvalidInputError, match="7 distinct"):
        BoundarySpline().fit(circle(7))
    with pytest.raises(InvalidInputError, match="5 distinct"):
        BoundarySpline().fit(np.repeat(circle(5), 4, axis=0))
    with pytest.raises(InvalidInputError, match="NaN"):
        BoundarySpline().fit(np.vstack([circle(20), [[np.nan, 0.0]]]))
    with pytest.raises(InvalidInputError, match="shape"):
        BoundarySpline().fit(np.zeros((20, 3)))
    for params in ({"lam": -1.0}, {"degree": 0}, {"variance": "median"}, {"n_samples": 4}):
        with pytest.raises(InvalidInputError, match=next(iter(params))):
            BoundarySpline(**params).fit(circle(20))
    with pytest.raises(FitError, match="too large"):
        BoundarySpline(lam=1.0).fit(circle(20))
    with pytest.raises(NotFittedError):
        BoundarySpline().evaluate(10)
    with pytest.raises(InvalidInputError, match="spacing"):
        BoundarySpline().fit(circle(20)).sample_by_spacing(0.0)
