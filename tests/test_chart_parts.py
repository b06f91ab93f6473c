"""A re-mesh skips the charts whose part of the join cannot change (reconstruct.chart_parts)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh

from reconstruct.atlas import AtlasReconstructor
from reconstruct.chart_parts import chart_part, deep_nodes, unchanged
from reconstruct.errors import ReconstructionWarning
from reconstruct.meshing import lattice_grid, lattice_nodes, mesh_inside, sample_ring

SPACING = 0.1


def square(half: float) -> np.ndarray:
    """A closed counter-clockwise square outline (5, 2)."""
    return np.array([[-half, -half], [half, -half], [half, half], [-half, half], [-half, -half]])


def flat(uv):
    return np.column_stack([uv, np.zeros(len(uv))])


def within(radius):
    return lambda xyz: np.hypot(xyz[:, 0], xyz[:, 1]) < radius


def flat_part(outline, radius):
    """The part of a flat chart (uv → (u, v, 0)) whose own part of the cloud is the disc of
    ``radius``, meshed with ``outline`` on the lattice of SPACING."""
    vertices_2d, faces = mesh_inside(outline, sample_ring(outline, SPACING), SPACING,
                                     lattice=True)
    mesh = trimesh.Trimesh(flat(vertices_2d), faces, process=False)
    kept = np.flatnonzero(within(radius)(mesh.vertices))
    return chart_part(mesh.vertices, vertices_2d, lattice_nodes(outline, SPACING), SPACING,
                      kept, mesh.vertex_normals[kept])


def test_deep_nodes_are_those_whose_neighbours_are_all_used():
    used = np.ones((5, 6), bool)
    used[0, 2] = False
    deep = deep_nodes(used)
    assert deep.sum() == 3 * 4 - 3  # the frame is not deep, nor the three beside the hole
    assert not deep[1, 1:4].any() and deep[1, 4] and deep[2, 1:5].all()


def test_an_outline_moving_away_from_the_charts_own_part_leaves_it_unchanged():
    part = flat_part(square(1.0), radius=0.5)
    assert part.nodes is not None and len(part.samples) > 50
    for half in (0.8, 1.0, 1.3):  # in, as it was, out: all far from the disc
        assert unchanged(part, square(half), SPACING, flat, within(0.5))


def test_an_outline_near_the_charts_own_part_changes_it():
    part = flat_part(square(1.0), radius=0.5)
    assert unchanged(part, square(0.55), SPACING, flat, within(0.5))  # just clear of it
    assert not unchanged(part, square(0.45), SPACING, flat, within(0.5))  # cuts the disc's
    # nodes out of the deep ones
    assert not unchanged(part, square(1.0), SPACING, flat, within(0.95))  # nodes near it owned


def test_a_part_that_reaches_its_outline_is_always_meshed():
    part = flat_part(square(1.0), radius=2.0)  # the whole chart is its own: border included
    assert part.nodes is None
    assert not unchanged(part, square(1.0), SPACING, flat, within(2.0))
    assert not unchanged(None, square(1.0), SPACING, flat, within(2.0))


@pytest.fixture(scope="module")
def torus_atlas():
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.4)
    points, _ = trimesh.sample.sample_surface_even(torus, 6000, seed=0)
    points = points + np.random.default_rng(0).normal(scale=0.005 * 2.8, size=points.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReconstructionWarning)
        return AtlasReconstructor(chart_size=1000, random_state=0).fit(points)


def test_remesh_skipping_charts_gives_the_mesh_of_meshing_them_all(torus_atlas):
    skipping = AtlasReconstructor.from_state(*torus_atlas.state())
    every = AtlasReconstructor.from_state(*torus_atlas.state())
    meshed = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReconstructionWarning)
        for change in ({}, {"lam": 2.0}, {"depth": 3}, {"lam": 0.5}, {"lam": 5.0},
                       {"depth": 1}, {"lam": 0.2}, {"lam": 1.0, "depth": 2}):
            mesh = skipping.remesh(**change)
            every.__dict__.pop("_parts", None)  # nothing kept: every chart meshed
            full = every.remesh(**change)
            assert every.remesh_counts_["charts meshed"] == len(every.charts_)
            np.testing.assert_allclose(mesh.vertices, full.vertices, rtol=0, atol=1e-9)
            np.testing.assert_array_equal(mesh.faces, full.faces)
            meshed.append(skipping.remesh_counts_["charts meshed"])
    assert meshed[0] < len(skipping.charts_)  # the state carries the fit's parts
    assert max(meshed) < len(skipping.charts_)  # some chart skipped every time
    skipped = [chart for chart in skipping.charts_ if not hasattr(chart, "mesh_")]
    assert all(chart.lam == 1.0 and chart.depth == 2 for chart in skipping.charts_)
    if skipped:  # its parameters taken, its mesh dropped; asked for, it meshes again
        assert len(skipped[0].remesh().faces) > 0


def test_a_join_that_needs_the_faces_of_skipped_charts_meshes_them_again(torus_atlas):
    skipping = AtlasReconstructor.from_state(*torus_atlas.state())
    every = AtlasReconstructor.from_state(*torus_atlas.state())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReconstructionWarning)
        skipping.remesh()
        skipping.remesh(lam=2.0)
        assert any("mesh_" not in vars(chart) for chart in skipping.charts_)
        every.remesh(lam=2.0)
        for atlas in (skipping, every):  # an open join fills the charts' stretched faces
            atlas.set_params(closed=False)
            atlas._join()
    assert all("mesh_" in vars(chart) for chart in skipping.charts_)
    np.testing.assert_allclose(skipping.mesh_.vertices, every.mesh_.vertices, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(skipping.mesh_.faces, every.mesh_.faces)


def test_a_loaded_atlas_skips_charts_at_its_first_remesh(torus_atlas, tmp_path):
    atlas = AtlasReconstructor.from_state(*torus_atlas.state())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReconstructionWarning)
        atlas.remesh()  # joined once: its parts are kept, and saved
        path = atlas.save(tmp_path / "atlas.npz")
        loaded, without = AtlasReconstructor.load(path), AtlasReconstructor.load(path)
        del without._parts  # as a state saved before the parts were
        for change in ({}, {"lam": 2.0}):
            mesh, full = loaded.remesh(**change), without.remesh(**change)
            np.testing.assert_allclose(mesh.vertices, full.vertices, rtol=0, atol=1e-9)
            np.testing.assert_array_equal(mesh.faces, full.faces)
    assert loaded.remesh_counts_["charts meshed"] < len(loaded.charts_)
    assert loaded.watertight_ and loaded.euler_ == without.euler_ == 0


def test_a_state_whose_parts_do_not_fit_its_charts_is_refused(torus_atlas, tmp_path):
    from reconstruct.errors import InvalidInputError
    from reconstruct.io import read_state, write_state

    atlas = AtlasReconstructor.from_state(*torus_atlas.state())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReconstructionWarning)
        atlas.remesh()
    meta, arrays = read_state(atlas.save(tmp_path / "atlas.npz"))
    arrays = {**arrays, "part1_normals": arrays["part1_normals"][:-1]}
    path = write_state(tmp_path / "bad.npz", meta, arrays)
    with pytest.raises(InvalidInputError, match="damaged atlas state.*parts"):
        AtlasReconstructor.load(path)


def test_a_shared_lattice_grid_meshes_and_tests_as_one_laid_afresh():
    outline = square(0.5)
    grid = lattice_grid(outline, SPACING)
    ring = sample_ring(outline, SPACING)
    for got, fresh in zip(mesh_inside(outline, ring, SPACING, lattice=True, grid=grid),
                          mesh_inside(outline, ring, SPACING, lattice=True), strict=True):
        np.testing.assert_array_equal(got, fresh)
    for got, fresh in zip(lattice_nodes(outline, SPACING, grid), lattice_nodes(outline, SPACING),
                          strict=True):
        np.testing.assert_array_equal(got, fresh)
    part = flat_part(square(1.0), 0.3)
    assert unchanged(part, outline, SPACING, flat, within(0.3), grid) == unchanged(
        part, outline, SPACING, flat, within(0.3))
