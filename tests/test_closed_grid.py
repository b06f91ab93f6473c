"""The closed join's signed grid: updated round the samples that changed, it equals a fresh one
node for node, and it gives the same mesh (reconstruct.closed_grid)."""

import numpy as np
import pytest
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from reconstruct.chart_sides import UnchartedTracker, uncharted_points
from reconstruct.closed_grid import BOX_SLACK, ClosedSDF
from reconstruct.grid_steps import (
    farther_than,
    free_pockets,
    grey_opening3,
    squared_distance,
    voter_sides,
)
from reconstruct.join import implicit_mesh

GRIDS = ["_occupied", "_free", "_exterior", "_closing", "_planes", "_nearest", "_ahead",
         "_eighth", "_held", "_values", "values_"]


def torus_samples(seed=0):
    """A torus's vertices, jittered (ties between equally near samples are arbitrary), with
    outward normals; genus 1, so the grid has a hole and an enclosed inside."""
    torus = trimesh.creation.torus(1.0, 0.35, major_sections=96, minor_sections=48)
    jitter = np.random.default_rng(seed).normal(0, 1e-4, torus.vertices.shape)
    return np.asarray(torus.vertices) + jitter, np.asarray(torus.vertex_normals)


def assert_same_grid(updated, fresh):
    assert np.array_equal(updated.origin_, fresh.origin_)
    for name in GRIDS:
        np.testing.assert_array_equal(getattr(updated, name), getattr(fresh, name), err_msg=name)
    assert updated._pockets[2] is not None  # the torus's inside: an enclosed pocket that votes
    for kept, new in zip(updated._voting, fresh._voting, strict=True):
        np.testing.assert_array_equal(kept, new)


@pytest.mark.parametrize("seal", [None, 6.0])
def test_an_update_equals_a_fresh_fit_and_evaluates_only_round_the_change(seal):
    samples, normals = torus_samples()
    kept_open = samples[:, 0] > 1.2  # one side's shell kept open in front
    grid = ClosedSDF(voxel=0.05, seal=seal).fit(samples, normals, kept_open)
    moved = samples.copy()
    dent = np.linalg.norm(samples - [0.95, 0.95, 0], axis=1) < 0.15  # not at the box's edge
    moved[dent] -= 0.04 * normals[dent]  # a dent on the outside
    gone = np.linalg.norm(samples - [-1.0, 0, 0.35], axis=1) < 0.12  # a hole on the top
    flags = kept_open.copy()
    flags[np.argmin(np.linalg.norm(samples - [0, -1.35, 0], axis=1))] = True  # one flag set
    keep = ~gone
    grid.update(moved[keep], normals[keep], flags[keep])
    fresh = ClosedSDF(voxel=0.05, seal=seal).fit(moved[keep], normals[keep], flags[keep])
    assert grid.n_changed_ == 2 * dent.sum() + gone.sum() + 2
    assert 0 < grid.n_evaluated_ < 0.2 * fresh.n_evaluated_
    assert_same_grid(grid, fresh)


def test_a_sample_moved_within_the_tolerance_then_removed_updates_its_nodes():
    """A sample that moves by less than the tolerance counts as the same: its nodes keep the
    distances to where it was. Removed later, every node it was among the 8 nearest of is
    evaluated again, though such a node is now a little farther from it than its eighth."""
    samples, normals = torus_samples(3)
    voxel, tolerance = 0.05, 1e-3 * 0.05
    grid = ClosedSDF(voxel=voxel, tolerance=tolerance).fit(samples, normals)
    near = np.linalg.norm(samples - [1.0, 0.0, 0.35], axis=1) < 0.1  # on the top, away
    drifted = samples.copy()
    drifted[near] += 0.9 * tolerance * normals[near]  # away from the nodes inside
    grid.update(drifted, normals)
    assert grid.n_changed_ == 0
    keep = ~near
    grid.update(drifted[keep], normals[keep])
    fresh = ClosedSDF(voxel=voxel, tolerance=tolerance).fit(drifted[keep], normals[keep])
    assert_same_grid(grid, fresh)


def test_the_box_is_kept_while_the_samples_fit_in_it_and_saved_with_the_state():
    samples, normals = torus_samples(2)
    voxel = 0.05
    grid = ClosedSDF(voxel=voxel).fit(samples, normals)
    origin, shape = grid.origin_.copy(), grid.shape_.copy()
    np.testing.assert_allclose(origin / voxel, np.round(origin / voxel), atol=1e-9)  # lattice
    assert np.abs(grid.values_).min() >= 1e-3 * voxel  # kept off the level
    saved = ClosedSDF.from_state(*grid.state())
    far = np.argmax(samples[:, 0])  # the sample that bounds the box along x
    moved = samples.copy()
    moved[far, 0] += 1.5 * voxel  # out by less than the slack
    grid.update(moved, normals)
    assert np.array_equal(grid.origin_, origin) and np.array_equal(grid.shape_, shape)
    assert grid.n_changed_ == 2 and 0 < grid.n_evaluated_ < 0.05 * grid.shape_.prod()
    assert_same_grid(grid, saved.fit(moved, normals))  # a loaded grid fits on its saved box
    moved[far, 0] += (BOX_SLACK + 1) * voxel  # (in place: the grid kept a copy) out of the box
    grid.update(moved, normals)
    assert grid.shape_[0] > shape[0] and grid.n_evaluated_ > 0.05 * grid.shape_.prod()
    assert_same_grid(grid, ClosedSDF(voxel=voxel).fit(moved, normals))
    shifted = ClosedSDF(voxel=voxel, shift=0.5).fit(samples, normals)  # half a voxel off
    np.testing.assert_allclose((shifted.origin_ - origin) / voxel % 1, 0.5, atol=1e-9)
    assert ClosedSDF.from_state(*shifted.state()).shift == 0.5


def test_uncharted_points_and_a_gap_update_like_a_fresh_fit():
    samples, normals = torus_samples(1)
    slit = np.abs(samples[:, 1]) < 0.03  # a slit across the tube, capped by the closing
    extra = samples[slit & (samples[:, 0] > 0)]  # data no chart holds, across one side
    grid = ClosedSDF(voxel=0.05).fit(samples[~slit], normals[~slit], uncharted=extra)
    refill = slit & (samples[:, 0] < 0)  # the other side's samples come back
    keep = ~slit | refill
    grid.update(samples[keep], normals[keep], uncharted=lambda tree, moved: extra[:-3])
    fresh = ClosedSDF(voxel=0.05).fit(samples[keep], normals[keep], uncharted=extra[:-3])
    assert grid.n_changed_ == refill.sum()
    assert_same_grid(grid, fresh)


def test_the_same_samples_in_another_order_change_nothing_and_a_saved_grid_refits():
    samples, normals = torus_samples()
    grid = ClosedSDF(voxel=0.06)
    first = implicit_mesh(samples, normals, voxel=0.06, closed=True, grid=grid)
    again = implicit_mesh(samples[::-1], normals[::-1], voxel=0.06, closed=True, grid=grid)
    assert grid.hit_ and grid.n_changed_ == 0 and grid.n_evaluated_ == 0
    assert np.array_equal(first.vertices, again.vertices)
    assert first.is_watertight and first.euler_number == 0  # the torus's genus
    loaded = ClosedSDF.from_state(*grid.state(prefix="join_"), prefix="join_")
    same = implicit_mesh(samples, normals, voxel=0.06, closed=True, grid=loaded)
    assert loaded.hit_ and np.array_equal(same.vertices, first.vertices)
    dent = np.linalg.norm(samples - [-0.95, 0.95, 0.3], axis=1) < 0.15
    bumped = samples - 0.03 * normals * dent[:, None]
    updated = implicit_mesh(bumped, normals, voxel=0.06, closed=True, grid=grid)
    refitted = implicit_mesh(bumped, normals, voxel=0.06, closed=True, grid=loaded)
    fresh = implicit_mesh(bumped, normals, voxel=0.06, closed=True)
    assert grid.n_changed_ == 2 * dent.sum() and grid.n_evaluated_ < 0.2 * loaded.n_evaluated_
    for mesh in (updated, refitted):
        np.testing.assert_array_equal(mesh.vertices, fresh.vertices)
        np.testing.assert_array_equal(mesh.faces, fresh.faces)


def test_a_pocket_voter_is_in_front_only_if_the_nearly_as_near_samples_agree():
    from scipy.spatial import cKDTree


    voter = np.zeros((1, 3))
    for other, expected in ((1.5, False), (2.5, True)):  # within a voxel farther, or beyond
        samples = np.array([[-1.0, 0, 0], [other, 0, 0]])  # the nearest faces the voter ...
        normals = np.array([[1.0, 0, 0], [1.0, 0, 0]])  # ... the other puts it behind
        distance, front = voter_sides(voter, samples, normals, cKDTree(samples), voxel=1.0)
        assert distance[0] == 1.0 and front[0] == expected


def test_a_mesh_kept_by_an_earlier_revision_of_the_join_is_not_given_back():
    samples, normals = torus_samples()
    grid = ClosedSDF(voxel=0.06)
    first = implicit_mesh(samples, normals, voxel=0.06, closed=True, grid=grid)
    meta, arrays = grid.state(prefix="join_")
    meta["mesh_key"][0] -= 1  # saved by the revision before this one
    arrays["join_mesh_vertices"] = arrays["join_mesh_vertices"][::-1]  # a different mesh
    older = ClosedSDF.from_state(meta, arrays, prefix="join_")
    again = implicit_mesh(samples, normals, voxel=0.06, closed=True, grid=older)
    assert not older.hit_ and np.array_equal(again.vertices, first.vertices)


@pytest.mark.parametrize("radius", [0.5, 1.0, 2.9, 3.0, np.sqrt(10.0), 4.5, 6.0, 7.0, 8.0, 12.5])
def test_capped_distances_are_scipys_within_their_radius(radius):

    rng = np.random.default_rng(int(radius * 10))
    for shape, share in (((40, 31, 17), 0.002), ((5, 60, 3), 0.02), ((9, 9, 9), 0.0015)):
        targets = rng.random(shape) < share
        targets.flat[rng.integers(targets.size)] = True
        exact = ndimage.distance_transform_edt(~targets)
        capped = np.sqrt(squared_distance(targets, radius).astype(float))
        near = exact <= radius
        np.testing.assert_array_equal(capped[near], exact[near])  # bit for bit
        assert (capped[~near] > radius).all()
        np.testing.assert_array_equal(farther_than(targets, radius), exact > radius)


@pytest.mark.parametrize("shape", [(1, 5, 7), (2, 2, 2), (9, 1, 4), (17, 12, 9), (3, 30, 5)])
def test_the_opening_is_scipys_node_for_node(shape):
    values = np.random.default_rng(sum(shape)).normal(size=shape)
    values[0, 0, 0] = values[-1, -1, -1] = 9.0  # extremes on the border
    np.testing.assert_array_equal(grey_opening3(values),
                                  ndimage.grey_opening(values, size=(3, 3, 3)))


def test_the_uncharted_tracker_finds_what_a_fresh_look_finds():
    samples, _ = torus_samples()
    rng = np.random.default_rng(4)
    spacing = 0.05
    # data the samples leave out: a cluster off the surface, and single points (noise)
    points = np.concatenate([samples[::3], samples[:40] * 1.3, rng.normal(size=(5, 3)) * 3])
    tracker = UnchartedTracker(points, spacing)
    steps = [samples, samples[:-300], np.concatenate([samples[:500], samples[700:]]),
             np.concatenate([samples[:500], samples[700:900] + 0.02, samples[900:]]),
             samples[::2], samples, np.concatenate([samples, [[9.0, -9.0, 9.0], [0.0, 0.0, 1.3]]])]
    sizes, before, looked_round = [], None, 0
    for step, now in enumerate(steps):
        tree = cKDTree(now)
        expected = uncharted_points(points, now, spacing, tree)
        moved = None if before is None else _rows_not_in_both(before, now)
        looked_round += moved is not None and 0 < len(moved) <= 0.25 * len(now)
        found = tracker(now, tree, moved)
        assert np.array_equal(found, expected), step
        sizes.append(len(found))
        before = now
    assert len(set(sizes)) >= 3, sizes  # the changes do change what is uncharted
    assert looked_round == 4  # four steps looked up only the points round the moved samples
    # (one moved far beyond the points, one beside them)


def _rows_not_in_both(old, new):
    """The rows (q, 3) of ``old`` or ``new`` that the other does not have."""
    a, b = {tuple(r) for r in old}, {tuple(r) for r in new}
    return np.array(sorted(a ^ b), float).reshape(-1, 3)


@pytest.mark.parametrize("share", [0.0, 0.3, 0.55, 0.8, 1.0])
def test_the_free_pockets_are_scipys_pieces(share):
    rng = np.random.default_rng(int(10 * share))
    free = rng.random((23, 17, 31)) < share
    free[5:9, 5:9, 5:9] = False  # a shell round an enclosed pocket
    free[6:8, 6:8, 6:8] = True
    pieces, border, _ = free_pockets(free)
    expected, count = ndimage.label(free)
    np.testing.assert_array_equal(pieces, expected)
    assert pieces.dtype == expected.dtype and len(border) == count + 1
    assert not border[0] and not border[pieces[7, 7, 7]]  # the pocket is enclosed
