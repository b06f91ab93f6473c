"""The join's distance grid: evaluated only near the samples, it equals the dense evaluation;
re-evaluated only near changed samples, it equals a fresh one (reconstruct.sdf_grid)."""

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from reconstruct.join import implicit_mesh
from reconstruct.sdf_grid import SparseSDF, changed_rows


def dense(samples, normals, voxel, band, origin, shape):
    """Every node of the box: the IMLS distance within band + 1 voxels, the mask within band."""
    axes = [origin[i] + voxel * np.arange(shape[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    tree = cKDTree(samples)
    distance = tree.query(grid, distance_upper_bound=(band + 1) * voxel)[0]
    near = np.isfinite(distance)
    values = np.full(len(grid), voxel * (band + 1))
    d, index = tree.query(grid[near], k=8)
    at = grid[near]  # (node − sample) · normal, summed as node · normal − sample · normal
    plane = np.einsum("mi,mi->m", samples, normals)
    offsets = -plane[index]
    for axis in range(3):
        offsets = offsets + normals[index, axis] * at[:, axis, None]
    weights = np.exp(-(d / (1.5 * voxel)) ** 2)
    values[near] = (weights * offsets).sum(axis=1) / weights.sum(axis=1)
    return values.reshape(shape), (distance <= band * voxel).reshape(shape)


def sphere_samples(subdivisions=3):
    """An icosphere's vertices, jittered: its symmetry puts many samples at exactly one
    distance from a node, and which of them is the 8th nearest is then arbitrary."""
    sphere = trimesh.creation.icosphere(subdivisions)
    jitter = np.random.default_rng(0).normal(0, 1e-4, sphere.vertices.shape)
    return np.asarray(sphere.vertices) + jitter, np.asarray(sphere.vertex_normals)


def assert_same_grid(sdf, fresh, voxel, atol=0.0):
    """Two grids on one lattice, node by node over the union of both boxes."""
    low = np.minimum(sdf.origin_, fresh.origin_)
    high = np.maximum(sdf.origin_ + voxel * (sdf.shape_ - 1),
                      fresh.origin_ + voxel * (fresh.shape_ - 1))
    size = tuple(np.round((high - low) / voxel).astype(int) + 1)

    def placed(grid, values, fill):
        out = np.full(size, fill, dtype=values.dtype)
        at = np.round((grid.origin_ - low) / voxel).astype(int)
        out[tuple(slice(a, a + n) for a, n in zip(at, grid.shape_, strict=True))] = values
        return out

    far = voxel * (sdf.band + 1)
    np.testing.assert_allclose(placed(sdf, sdf.values_, far), placed(fresh, fresh.values_, far),
                               atol=atol, rtol=0)
    assert np.array_equal(placed(sdf, sdf.mask_, False), placed(fresh, fresh.mask_, False))


def test_the_sparse_grid_equals_the_dense_one():
    samples, normals = sphere_samples(4)
    sdf = SparseSDF(voxel=0.05, band=2.0).fit(samples, normals)
    values, mask = dense(samples, normals, 0.05, 2.0, sdf.origin_, sdf.shape_)
    assert np.array_equal(sdf.mask_, mask) and mask.sum() > 1000
    np.testing.assert_array_equal(sdf.values_, values)
    assert sdf.n_evaluated_ < 0.5 * mask.size  # the inside and the corners are never queried
    assert np.allclose(sdf.origin_ / 0.05, np.round(sdf.origin_ / 0.05))  # on the lattice


def test_an_update_equals_a_fresh_fit_and_touches_only_the_change():
    samples, normals = sphere_samples()
    sdf = SparseSDF(voxel=0.1, band=2.0).fit(samples, normals)
    top = samples[:, 2] > 0.9
    moved = samples.copy()
    moved[top] *= 1.05  # a bump on the top
    kept = np.flatnonzero(samples[:, 0] < 0.95)  # and a few samples gone on one side
    sdf.update(moved[kept], normals[kept])
    fresh = SparseSDF(voxel=0.1, band=2.0).fit(moved[kept], normals[kept])
    assert sdf.n_changed_ == top.sum() + (len(samples) - len(kept)) + top[kept].sum()
    assert sdf.n_evaluated_ < 0.5 * fresh.n_evaluated_
    assert_same_grid(sdf, fresh, 0.1, atol=1e-12)


def test_a_sample_moved_within_the_tolerance_then_removed_updates_its_nodes():
    samples, normals = sphere_samples(2)  # sparse: most nodes' 8th nearest beyond the band
    voxel, tolerance = 0.1, 1e-4
    sdf = SparseSDF(voxel=voxel, band=2.0, tolerance=tolerance).fit(samples, normals)
    top = samples[:, 2] > 0.97
    drifted = samples.copy()
    drifted[top] += 0.9 * tolerance * normals[top]  # the same, to the tolerance
    sdf.update(drifted, normals)
    assert sdf.n_changed_ == 0
    sdf.update(drifted[~top], normals[~top])  # then gone
    fresh = SparseSDF(voxel=voxel, band=2.0, tolerance=tolerance).fit(drifted[~top],
                                                                     normals[~top])
    assert_same_grid(sdf, fresh, voxel)


def test_the_same_samples_give_back_the_same_mesh_at_once():
    samples, normals = sphere_samples(4)
    grid = SparseSDF(voxel=0.08)
    first = implicit_mesh(samples, normals, voxel=0.08, grid=grid)
    again = implicit_mesh(samples[::-1], normals[::-1], voxel=0.08, grid=grid)  # reordered
    assert grid.n_changed_ == 0 and grid.n_evaluated_ == 0
    assert np.array_equal(first.vertices, again.vertices) and again.is_watertight
    bumped = samples * np.where(samples[:, 2:] > 0.95, 1.03, 1.0)
    updated = implicit_mesh(bumped, normals, voxel=0.08, grid=grid)
    fresh = implicit_mesh(bumped, normals, voxel=0.08)
    assert 0 < grid.n_changed_ < 0.05 * len(samples)
    assert len(updated.vertices) == len(fresh.vertices)
    np.testing.assert_allclose(np.sort(updated.vertices, axis=0), np.sort(fresh.vertices, axis=0),
                               atol=1e-9)


def test_a_saved_grid_continues_where_it_stopped():
    samples, normals = sphere_samples()
    sdf = SparseSDF(voxel=0.1, band=2.0).fit(samples, normals)
    loaded = SparseSDF.from_state(*sdf.state(prefix="join_"), prefix="join_")
    assert np.array_equal(loaded.values_, sdf.values_) and np.array_equal(loaded.mask_, sdf.mask_)
    bumped = samples * np.where(samples[:, 2:] > 0.9, 1.05, 1.0)
    loaded.update(bumped, normals)
    sdf.update(bumped, normals)
    assert loaded.n_changed_ == sdf.n_changed_ > 0
    np.testing.assert_array_equal(loaded.values_, sdf.values_)


def test_farther_than_answers_as_the_tree_does():
    """The grid's own nearest distances decide most points; the answer is the tree's at every
    point, after an update, and from a state saved with or without those distances."""
    samples, normals = sphere_samples(3)
    samples, normals = samples[samples[:, 2] < 0.6], normals[samples[:, 2] < 0.6]  # a hole
    sdf = SparseSDF(voxel=0.1, band=2.0).fit(samples, normals)
    rng = np.random.default_rng(1)
    inside = sdf.origin_ + 0.1 * (sdf.shape_ - 1) * rng.random((20000, 3))
    on_surface = samples[rng.integers(len(samples), size=5000)] + rng.normal(0, 0.05, (5000, 3))
    beyond = sdf.origin_ + 0.1 * (sdf.shape_ - 1) * rng.uniform(-0.5, 1.5, (3000, 3))
    points = np.vstack([inside, on_surface, beyond])  # (some beyond the grid's box)
    for distance in (0.05, 0.15, 0.3):
        truth = cKDTree(sdf.samples_).query(points)[0] > distance
        assert np.array_equal(sdf.farther_than(points, distance), truth)
        assert 0 < truth.sum() < len(points)
    bumped = samples * np.where(samples[:, 2:] > 0.3, 1.04, 1.0)
    sdf.update(bumped, normals)
    meta, arrays = sdf.state()
    old = SparseSDF.from_state(meta, {k: v for k, v in arrays.items() if k != "first"})
    for grid in (sdf, SparseSDF.from_state(meta, arrays), old):
        truth = cKDTree(bumped).query(points)[0] > 0.15
        assert np.array_equal(grid.farther_than(points, 0.15), truth)


def test_changed_rows_finds_a_change_between_unchanged_ends():
    rng = np.random.default_rng(3)
    old, old_normals = rng.normal(size=(100, 3)), rng.normal(size=(100, 3))
    fresh = rng.normal(size=(5, 3))
    flags = np.r_[[False] * 100, [True] * 5]
    cases = {  # new samples and normals, which of them are new, which old ones are gone
        "middle replaced": (np.r_[old[:40], fresh, old[50:]],
                            np.r_[old_normals[:40], fresh, old_normals[50:]],
                            np.r_[flags[:40], flags[-5:], flags[:50]], np.arange(40, 50)),
        "cut short": (old[:70], old_normals[:70], flags[:70], np.arange(70, 100)),
        "grown": (np.r_[old, fresh], np.r_[old_normals, fresh], flags, []),
        "one normal turned": (old, np.r_[old_normals[:99], -old_normals[99:]],
                              np.arange(100) == 99, [99]),
        "moved within tolerance": (old + 1e-12, old_normals, flags[:100], []),
        "a row of an end again in the middle": (np.r_[old[:40], old[:1], old[41:]],
                                                np.r_[old_normals[:40], old_normals[:1],
                                                      old_normals[41:]],
                                                np.arange(100) == 40, [40]),
    }
    for name, (samples, normals, added, removed) in cases.items():
        got_added, got_removed = changed_rows(old, old_normals, cKDTree(old), samples, normals,
                                              1e-9, 1.0)
        assert np.array_equal(got_added, added), name
        assert np.array_equal(np.flatnonzero(got_removed), removed), name
    got_added, got_removed = changed_rows(old, old_normals, cKDTree(old), old, old_normals,
                                          1e-9, 1.0, flags[:100], np.arange(100) == 50)
    assert np.flatnonzero(got_added).tolist() == np.flatnonzero(got_removed).tolist() == [50]
