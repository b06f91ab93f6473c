"""A chart's residual field puts back the shape its mesh smoothed over, and leaves a mesh that
holds its shape as it is."""

import numpy as np
import pytest
import trimesh

from reconstruct import residual_detail
from reconstruct.residual_detail import ResidualDetail

SIGMA = 0.01


def flat_mesh():
    square = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]],
                             [[0, 1, 2], [0, 2, 3]])
    return trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(square.vertices, square.faces, 0.05))


def ridge(xy):
    """Ridges 0.5 wide and a noise width high, which a flat mesh leaves unfitted."""
    return SIGMA * np.sin(2 * np.pi * xy[:, 0] / 0.5)


def flat(xy):
    return np.zeros(len(xy))


def cloud(shape, n=6000, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n, 2))
    return np.column_stack([xy, shape(xy) + rng.normal(0, SIGMA, n)])


def probes(n=2000, seed=1):
    """(n, 3) samples on the flat mesh, away from its border, and their normals."""
    xy = np.random.default_rng(seed).uniform(-0.8, 0.8, (n, 2))
    return np.column_stack([xy, np.zeros(n)]), np.tile([0.0, 0.0, 1.0], (n, 1))


def test_the_shape_left_in_the_residuals_is_put_back():
    mesh, points = flat_mesh(), cloud(ridge)
    spacing = 2 / np.sqrt(len(points))
    detail = ResidualDetail(width=1.5 * spacing).fit(mesh, points)
    assert detail.shape_ > 0.25 * detail.variance_  # the ridge's share: a third
    samples, normals = probes()
    moved = detail.moved(samples, normals)
    truth = ridge(samples[:, :2])
    before = np.sqrt(np.mean(truth ** 2))  # the flat mesh's error
    after = np.sqrt(np.mean((moved[:, 2] - truth) ** 2))
    assert after < 0.6 * before
    np.testing.assert_array_equal(moved[:, :2], samples[:, :2])  # along the normals only


def test_noise_alone_leaves_the_samples_as_they_are():
    mesh = flat_mesh()
    spacing = 2 / np.sqrt(6000)
    samples, normals = probes()
    for seed in range(3):
        detail = ResidualDetail(width=1.5 * spacing).fit(mesh, cloud(flat, seed=seed))
        assert detail.shape_ < 0.05 * detail.variance_
        moved = detail.moved(samples, normals)
        # the noise left in the average, shrunk by how little shape it holds
        assert np.sqrt(np.mean((moved - samples) ** 2)) < 0.1 * SIGMA


def test_a_mesh_that_holds_its_shape_moves_nothing():
    mesh = flat_mesh()
    detail = ResidualDetail(width=0.05).fit(mesh, cloud(flat))
    detail.shape_ = 0.0  # nothing shared along the mesh
    samples, normals = probes()
    assert detail.moved(samples, normals) is samples
    assert not detail.offsets(samples).any()
    empty = ResidualDetail(width=0.05).fit(mesh, np.zeros((0, 3)))
    assert empty.moved(samples, normals) is samples


def test_a_field_taken_back_from_its_parts_moves_samples_alike():
    mesh, points = flat_mesh(), cloud(ridge)
    detail = ResidualDetail(width=0.04).fit(mesh, points)
    again = ResidualDetail(width=0.04).set_fitted(points, detail.residuals_, detail.variance_,
                                                  detail.shape_)
    samples, normals = probes()
    np.testing.assert_array_equal(again.moved(samples, normals), detail.moved(samples, normals))


@pytest.mark.parametrize("n", [1, 5])
def test_a_chart_of_few_points_still_gives_offsets(n):
    mesh, points = flat_mesh(), cloud(ridge, n=n)
    detail = ResidualDetail(width=0.04).fit(mesh, points)
    assert detail.shape_ == 0.0  # too few to tell shape from noise
    samples, normals = probes(10)
    assert detail.moved(samples, normals) is samples


def test_points_in_two_layers_are_no_shape_to_put_back(monkeypatch):
    """The two faces of a plate charted once, one face's points crowding the other's in
    patches: their residuals are shared along the mesh, but they are two layers (kurtosis
    under `faithfulness.LAYERED_KURTOSIS`), which no move of the samples fits."""
    mesh = flat_mesh()

    def faces(xy):  # patches 0.1 wide of one face or the other, 2σ either side
        return 2 * SIGMA * np.sign(np.sin(np.pi * xy[:, 0] / 0.1) * np.sin(np.pi * xy[:, 1] / 0.1))

    points = cloud(faces)
    assert ResidualDetail(width=0.04).fit(mesh, points).shape_ == 0.0
    monkeypatch.setattr(residual_detail, "LAYERED_KURTOSIS", 0.0)
    assert ResidualDetail(width=0.04).fit(mesh, points).shape_ > 0.5 * SIGMA ** 2


def test_offsets_known_before_are_taken_bit_for_bit():
    mesh, points = flat_mesh(), cloud(ridge)
    detail = ResidualDetail(width=1.5 * 2 / np.sqrt(len(points))).fit(mesh, points)
    samples, _ = probes()
    before = detail.offsets(samples[:1500])
    # a re-mesh: some vertices kept (in another order), some new
    again = np.vstack([samples[1000:], samples[:400][::-1]])
    known = detail.offsets(again, known=(samples[:1500], before))
    np.testing.assert_array_equal(known, detail.offsets(again))
    # a row that moved by one ulp is no longer known, and is found afresh
    nudged = again.copy()
    nudged[0, 0] = np.nextafter(nudged[0, 0], 1.0)
    assert residual_detail.rows_among(samples[:1500], nudged)[0] == -1
    np.testing.assert_array_equal(detail.offsets(nudged, known=(samples[:1500], before)),
                                  detail.offsets(nudged))
    # a part that had no vertices before
    np.testing.assert_array_equal(detail.offsets(again, known=(samples[:0], before[:0])),
                                  detail.offsets(again))


def test_rows_among_finds_each_row_or_none():
    rows = np.array([[0.0, 1, 2], [3, 4, 5], [0, 1, 2.5]])
    queries = np.array([[3.0, 4, 5], [0, 1, 2], [9, 9, 9], [0, 1, 2.5]])
    np.testing.assert_array_equal(residual_detail.rows_among(rows, queries), [1, 0, -1, 2])
    np.testing.assert_array_equal(residual_detail.rows_among(np.zeros((0, 3)), queries),
                                  [-1] * 4)
