"""reconstruct.kdtree.PointTree answers as scipy's cKDTree does."""

import pickle

import numpy as np
import pytest
from scipy.spatial import cKDTree

from reconstruct.kdtree import PointTree


@pytest.mark.parametrize("n", [0, 1, 5, 2000])
@pytest.mark.parametrize("m", [0, 1, 300])
@pytest.mark.parametrize("dimension", [2, 3])
def test_the_same_neighbours_and_distances_as_ckdtree(n, m, dimension):
    rng = np.random.default_rng(n + m)
    points, queries = rng.random((n, dimension)), rng.random((m, dimension))
    ours, theirs = PointTree(points), cKDTree(points)
    for k in (1, 3, 8):  # k = 8 > n: the missing ones at inf, index n
        for bound in (np.inf, 0.05):  # beyond the bound: inf, index n
            for workers in (1, 2):
                got = ours.query(queries, k=k, distance_upper_bound=bound, workers=workers)
                want = theirs.query(queries, k=k, distance_upper_bound=bound)
                for a, b in zip(got, want, strict=True):
                    assert a.shape == np.shape(b)
                    np.testing.assert_array_equal(a, b)


def test_a_tree_pickles_and_a_grid_with_one_too():
    from reconstruct.closed_grid import ClosedSDF

    rng = np.random.default_rng(0)
    points = rng.normal(size=(500, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    tree = pickle.loads(pickle.dumps(PointTree(points)))
    np.testing.assert_array_equal(tree.query(points[:10], k=2)[1][:, 0], np.arange(10))
    grid = ClosedSDF(voxel=0.2).fit(points, points)
    again = pickle.loads(pickle.dumps(grid))
    np.testing.assert_array_equal(again.tree_.query(points, k=3)[0],
                                  grid.tree_.query(points, k=3)[0])
