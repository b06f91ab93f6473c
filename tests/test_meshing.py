import numpy as np
import pytest
import shapely

from reconstruct.errors import FitError
from reconstruct.meshing import MAX_GRID_NODES, default_spacing, lattice_grid, mesh_inside


def _loop(radius_fn, n=1200):
    t = np.linspace(0, 2 * np.pi, n)
    r = radius_fn(t)
    polygon = np.column_stack([r * np.cos(t), r * np.sin(t)])
    polygon[-1] = polygon[0]
    return polygon


def _areas(vertices, faces):
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return 0.5 * (
        (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    )


def _edge_counts(faces):
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return counts


SHAPES = {
    "circle": lambda t: np.ones_like(t),
    "trefoil": lambda t: 1 + 0.3 * np.cos(3 * t),
    "star": lambda t: 1 + 0.45 * np.cos(5 * t),  # strongly concave
}


@pytest.mark.parametrize("name", sorted(SHAPES))
@pytest.mark.parametrize("n_points", [300, 5000])
@pytest.mark.parametrize("lattice", [False, True])
def test_mesh_covers_the_polygon_once_with_ccw_manifold_triangles(name, n_points, lattice):
    # (the grid's squares are co-circular: qhull's joggled triangulation of the band must
    # still give whole, non-degenerate triangles)
    polygon = _loop(SHAPES[name])
    boundary = polygon[:-1:6]
    spacing = default_spacing(polygon, n_points)
    vertices, faces = mesh_inside(polygon, boundary, spacing, lattice=lattice)

    areas = _areas(vertices, faces)
    assert (areas > 0).all(), "every triangle counter-clockwise and non-degenerate"
    # Triangulating the boundary points' polygon exactly: area equals that polygon's area.
    expected = shapely.Polygon(boundary).area
    assert areas.sum() == pytest.approx(expected, rel=2e-3)
    assert _edge_counts(faces).max() == 2, "no edge shared by more than two triangles"
    # About as many vertices as points: the density rule.
    assert 0.6 * n_points < len(vertices) < 1.6 * n_points
    centroids = vertices[faces].mean(axis=1)
    assert shapely.contains_xy(shapely.Polygon(polygon), centroids[:, 0], centroids[:, 1]).all()


def test_grid_is_regular_inside():
    polygon = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]], dtype=float)
    t = np.linspace(0, 1, 41)[:-1]
    boundary = np.vstack(
        [
            np.column_stack([10 * t, 0 * t]),
            np.column_stack([10 + 0 * t, 10 * t]),
            np.column_stack([10 - 10 * t, 10 + 0 * t]),
            np.column_stack([0 * t, 10 - 10 * t]),
        ]
    )
    vertices, faces = mesh_inside(polygon, boundary, spacing=0.5)
    interior = vertices[(vertices > 0.6).all(axis=1) & (vertices < 9.4).all(axis=1)]
    # interior vertices on the 0.5 lattice
    np.testing.assert_allclose(np.round(interior * 2) / 2, interior, atol=1e-9)
    assert _areas(vertices, faces).sum() == pytest.approx(100.0, rel=1e-9)


def test_bad_spacing_is_an_error():
    polygon = _loop(SHAPES["circle"])
    with pytest.raises(FitError, match="spacing"):
        mesh_inside(polygon, polygon[:-1:10], spacing=0.0)


@pytest.mark.parametrize("lattice", [False, True])
def test_a_grid_too_fine_for_memory_is_refused_before_it_is_laid(lattice):
    polygon = _loop(SHAPES["circle"])  # 1e-9: 1e19 nodes, an overflow in int64 arithmetic
    assert (np.ptp(polygon, axis=0) / 1e-9).prod() > 1e4 * MAX_GRID_NODES
    with pytest.raises(FitError, match="grid spacing of 1e-09 lays .* nodes"):
        mesh_inside(polygon, polygon[:-1:10], spacing=1e-9, lattice=lattice)
    with pytest.raises(FitError, match="larger --spacing"):
        lattice_grid(polygon, 1e-9)


def test_on_the_lattice_a_new_outline_keeps_the_interior_nodes():
    angle = np.linspace(0, 2 * np.pi, 200)
    small = np.c_[np.cos(angle), np.sin(angle)]
    large = np.c_[1.13 * np.cos(angle) + 0.021, 1.07 * np.sin(angle) - 0.013]
    meshes = [mesh_inside(ring, ring[:-1:4], 0.1, lattice=True)[0] for ring in (small, large)]
    inner = meshes[0][np.linalg.norm(meshes[0], axis=1) < 0.8]  # well inside both outlines
    assert len(inner) > 150
    assert np.isin(inner.view(complex), meshes[1].view(complex)).all()  # the very same nodes
    off = [mesh_inside(ring, ring[:-1:4], 0.1)[0] for ring in (small, large)]
    inner = off[0][np.linalg.norm(off[0], axis=1) < 0.8]
    assert not np.isin(inner.view(complex), off[1].view(complex)).any()  # each its own grid
