"""The outward correction of the boundary outline (reconstruct.outline) and its use in meshing."""

import numpy as np
import pytest
import shapely
from scipy.spatial import cKDTree

from reconstruct.boundary import MultiDepthBoundary
from reconstruct.errors import InvalidInputError
from reconstruct.outline import BORDER_INSET, border_inset, border_spacing, extend_outline
from reconstruct.pipeline import SurfaceReconstructor
from reconstruct.spline import BoundarySpline


def uniform_square(n, seed):
    return np.random.default_rng(seed).uniform(size=(n, 2))


def test_border_spacing_counts_only_the_part_of_each_disk_inside():
    uv = uniform_square(4000, 0)
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]], dtype=float)
    spacing = border_spacing(square, cKDTree(uv))
    # k / area(disk ∩ square): the true spacing within sampling error; the whole disk would
    # read about √2 too large on the sides and 2 at the corners
    assert spacing == pytest.approx(np.sqrt(1 / 4000), rel=0.1)
    assert border_spacing(square * 10 + 3, cKDTree(uv * 10 + 3)) == pytest.approx(10 * spacing)


def test_extend_outline_grows_by_the_distance_and_keeps_orientation():
    t = np.linspace(0, 2 * np.pi, 257)
    circle = np.column_stack([np.cos(t), np.sin(t)])
    grown = extend_outline(circle, 0.1)
    assert np.hypot(*grown.T) == pytest.approx(1.1, abs=2e-3)
    assert shapely.LinearRing(grown).is_ccw == shapely.LinearRing(circle).is_ccw
    assert shapely.LinearRing(extend_outline(circle[::-1], 0.1)).is_ccw is False
    assert extend_outline(circle, 0) is circle


@pytest.mark.parametrize("depth", [1, 2])
@pytest.mark.parametrize("measured_on", ["spline", "interpolants"])
def test_the_calibrated_inset_restores_the_sampled_area(depth, measured_on):
    # The constants were measured on squares, 5:1 rectangles and disks; a fresh seed on a disk
    # must come out within about one standard deviation (0.15 spacing) of the true area, with
    # the spacing measured on the spline (as calibrated) or on the loop of its interpolants (as
    # the pipeline measures it, once for every λ).
    rng = np.random.default_rng(11)
    r, a = np.sqrt(rng.uniform(size=6000)), rng.uniform(0, 2 * np.pi, 6000)
    uv = np.column_stack([r * np.cos(a), r * np.sin(a)])
    interpolants = MultiDepthBoundary(depth=depth).fit(uv).points_
    spline = BoundarySpline(lam=1.0, variance="local").fit(interpolants)
    loop = np.vstack([interpolants, interpolants[:1]])
    spacing = border_spacing(spline.polygon_ if measured_on == "spline" else loop, cKDTree(uv))
    before = shapely.Polygon(spline.polygon_)
    after = shapely.Polygon(extend_outline(spline.polygon_, border_inset(depth) * spacing))
    tolerance = 0.15 * spacing * after.length
    assert before.area < np.pi - tolerance
    assert abs(after.area - np.pi) < tolerance
    assert border_inset(9) == BORDER_INSET[max(BORDER_INSET)]


def test_reconstructor_extend_options_and_errors():
    rng = np.random.default_rng(3)
    uv = rng.uniform(-1, 1, size=(900, 2))
    points = np.column_stack([uv, 0.3 * uv[:, 0] + rng.normal(0, 0.01, 900)])
    model = SurfaceReconstructor(random_state=0, max_neurons=3, max_layers=1).fit(points)
    areas = {}
    for extend in (0, "auto", "border", 1.5):
        model.remesh(extend=extend)
        areas[extend] = shapely.Polygon(model.outline_).area
        region = shapely.Polygon(model.outline_)
        x, y = model.vertices_2d_.T
        assert shapely.contains_xy(region.buffer(1e-9), x, y).all()
    assert areas[0] == pytest.approx(shapely.Polygon(model.spline_.polygon_).area)
    assert areas[0] < areas["auto"] < areas["border"] < areas[1.5]
    for bad in (-1, "far", float("nan")):
        with pytest.raises(InvalidInputError, match="extend"):
            model.remesh(extend=bad)
    model.remesh()  # the rejected values left the model as it was
    assert shapely.Polygon(model.outline_).area == pytest.approx(areas[1.5])


def test_every_lambda_extends_its_spline_by_the_same_spacing():
    # the points' spacing along the boundary is measured on the interpolants' loop, once: a
    # new λ moves the spline, not the distance it is grown by
    rng = np.random.default_rng(5)
    uv = rng.uniform(-1, 1, size=(1200, 2))
    points = np.column_stack([uv, 0.2 * uv[:, 1] ** 2 + rng.normal(0, 0.01, 1200)])
    model = SurfaceReconstructor(random_state=0, max_neurons=3, max_layers=1, depth=2)
    model.fit(points)
    grown = []
    for lam in (1.0, 2.0, 4.0):
        model.remesh(lam=lam)
        polygon, outline = model.spline_.polygon_, model.outline_
        assert len(outline) == len(polygon)  # grown along the normals, not buffered
        grown.append(np.median(np.hypot(*(outline - polygon).T)))
    spacing = model._border_spacing(model._boundary_points()[1])
    expected = (border_inset(2) - border_inset(1)) * spacing
    assert grown == pytest.approx([expected] * 3, rel=1e-6)


def test_extend_outline_falls_back_to_a_buffer_where_offsets_fold():
    # a square with a notch 0.02 wide: moving the vertices 0.05 along their normals crosses it
    notch = np.array([[0, 0], [1, 0], [1, 1], [0.51, 1], [0.51, 0.5], [0.49, 0.5], [0.49, 1],
                      [0, 1], [0, 0]], dtype=float)
    grown = extend_outline(notch, 0.05)
    ring = shapely.LinearRing(grown)
    assert ring.is_simple and ring.is_ccw
    assert shapely.Polygon(grown).contains(shapely.Polygon(notch))
    assert shapely.Polygon(grown).area == pytest.approx(
        shapely.Polygon(notch).buffer(0.05, quad_segs=8).area, rel=1e-9
    )


def test_a_loaded_model_prepared_for_remeshing_meshes_as_one_that_is_not():
    rng = np.random.default_rng(8)
    uv = rng.uniform(-1, 1, size=(1000, 2))
    points = np.column_stack([uv, 0.3 * np.sin(2 * uv[:, 0]) + rng.normal(0, 0.01, 1000)])
    model = SurfaceReconstructor(random_state=0, max_neurons=3, max_layers=1, depth=2)
    model.fit(points)
    model.sample_boundaries([1, 2, 3])
    prepared, plain = (SurfaceReconstructor.from_state(*model.state()) for _ in range(2))
    prepared.prepare_remeshing()
    spacings = prepared._boundary_cache["border spacing"]
    assert {key[1] for key in spacings} == {2, 3}  # depth 1 is not grown ("auto")
    measured = dict(spacings)
    for params in ({"lam": 2.0}, {"depth": 3}, {"lam": 0.5, "depth": 1}):
        a, b = prepared.remesh(**params), plain.remesh(**params)
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert all(spacings[key] is measured[key] for key in measured)  # not measured again
