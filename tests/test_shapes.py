"""Synthetic shapes (sim.shapes): ground truth that is really true."""

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from reconstruct.metrics import distance_to_surface
from sim.shapes import SHAPES, SyntheticShape, make_shape, torus_surface


def diagonal(shape):
    return float(np.linalg.norm(np.ptp(shape.truth.vertices, axis=0)))


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_every_shape_is_consistent(name):
    shape = make_shape(name, 144, noise=0.01, random_state=3)
    assert isinstance(shape, SyntheticShape) and shape.name == name
    assert shape.points.shape == shape.clean.shape == (144, 3)
    assert shape.params.shape == (144, 2)
    assert shape.noise_sigma == pytest.approx(0.01 * diagonal(shape))
    # Clean points lie on the truth mesh (its chord error is below 1e-4 of the diagonal).
    assert distance_to_surface(shape.truth, shape.clean).max() < 1e-4 * diagonal(shape)
    # The noise is what it claims: each coordinate's error ~ N(0, σ).
    error = (shape.points - shape.clean).ravel()
    assert np.std(error) == pytest.approx(shape.noise_sigma, rel=0.12)
    assert abs(np.mean(error)) < 0.2 * shape.noise_sigma


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_truth_mesh_is_dense_and_accurate(name):
    shape = make_shape(name, 3000, noise=0.0, random_state=0)
    assert len(shape.truth.faces) > 10_000
    assert distance_to_surface(shape.truth, shape.clean).max() < 1e-4 * diagonal(shape)


def test_zero_noise_gives_clean_points_and_seeds_are_reproducible():
    a = make_shape("saddle", 500, noise=0.0, random_state=1)
    np.testing.assert_array_equal(a.points, a.clean)
    assert a.noise_sigma == 0.0
    b = make_shape("saddle", 500, noise=0.02, random_state=1)
    c = make_shape("saddle", 500, noise=0.02, random_state=1)
    d = make_shape("saddle", 500, noise=0.02, random_state=2)
    np.testing.assert_array_equal(b.points, c.points)
    assert not np.allclose(b.points, d.points)


def test_s_curve_follows_scikit_learn():
    shape = make_shape("s_curve", 400, noise=0.0, random_state=0)
    t, height = shape.params.T
    assert t.min() >= -1.5 * np.pi and t.max() <= 1.5 * np.pi
    assert height.min() >= 0 and height.max() <= 2
    expected = np.column_stack([np.sin(t), height, np.sign(t) * (np.cos(t) - 1)])
    np.testing.assert_allclose(shape.clean, expected, atol=1e-12)


@pytest.mark.parametrize(("name", "upper"), [("torus_quarter", np.pi / 2), ("torus_half", np.pi)])
def test_torus_patches(name, upper):
    shape = make_shape(name, 300, noise=0.0, random_state=0)
    assert shape.params.min() >= 0 and shape.params.max() <= upper
    assert shape.params.max() > 0.95 * upper  # the whole domain is used
    # Every clean point is at the minor radius from the tube's centre circle (R = 1, r = 0.4).
    ring = np.hypot(shape.clean[:, 0], shape.clean[:, 1])
    np.testing.assert_allclose(np.hypot(ring - 1.0, shape.clean[:, 2]), 0.4, atol=1e-12)
    np.testing.assert_allclose(torus_surface(shape.params), shape.clean)


@pytest.mark.parametrize(("name", "side"), [("sparse_cone", 6), ("dense_cone", 12)])
def test_paper_cones_are_regular_grids(name, side):
    shape = SHAPES[name]()
    assert len(shape.points) == side * side
    for column in shape.params.T:
        values = np.unique(column)
        assert len(values) == side
        np.testing.assert_allclose(np.diff(values), np.diff(values)[0])
    # On the cone: radius = 0.5 (1 - z), height 1.
    radius = np.hypot(shape.clean[:, 0], shape.clean[:, 1])
    np.testing.assert_allclose(radius, 0.5 * (1 - shape.clean[:, 2]), atol=1e-12)


def test_sphere_cap_params_are_arc_lengths_from_the_pole():
    shape = make_shape("sphere_cap", 800, noise=0.0, random_state=0)
    np.testing.assert_allclose(np.linalg.norm(shape.clean, axis=1), 1.0, atol=1e-12)
    polar = np.arccos(np.clip(shape.clean[:, 2], -1, 1))
    np.testing.assert_allclose(polar, np.linalg.norm(shape.params, axis=1), atol=1e-9)
    assert polar.max() <= np.pi / 3 + 1e-12
    grid = make_shape("sphere_cap", 800, grid=True)
    assert np.linalg.norm(grid.params, axis=1).max() <= np.pi / 3


def test_terrain_and_saddle_are_height_fields_of_their_params():
    saddle = make_shape("saddle", 400, random_state=0)
    x, y = saddle.params.T
    np.testing.assert_allclose(saddle.clean, np.column_stack([x, y, 0.5 * (x**2 - y**2)]))
    a = make_shape("terrain", 400, random_state=0)
    b = make_shape("terrain", 400, random_state=1)
    np.testing.assert_array_equal(a.truth.vertices, b.truth.vertices)  # same terrain
    np.testing.assert_array_equal(a.clean[:, :2], a.params)
    assert np.ptp(a.clean[:, 2]) > 0.1  # it has relief


def test_arrays_are_read_only_and_the_shape_is_frozen():
    shape = make_shape("saddle", 100, noise=0.01, random_state=0)
    with pytest.raises(ValueError):
        shape.points[0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        shape.name = "other"


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown shape"):
        make_shape("teapot", 100)
    with pytest.raises(ValueError, match="factor pair"):
        make_shape("saddle", 37, grid=True)
    with pytest.raises(ValueError, match="noise"):
        make_shape("saddle", 100, noise=-0.1)


def test_shapes_import_nothing_of_reconstruct_or_capture():
    code = (
        "import sys, sim.shapes; "
        "bad = [m for m in sys.modules if m.split('.')[0] in ('reconstruct', 'capture')]; "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
