"""Outliers, neighbourhood graph, choice of K and the 3D → 2D embedding (known answers)."""

import logging
import warnings

import numpy as np
import pytest
from scipy.spatial import procrustes
from sklearn.base import clone

from reconstruct.embedding import SurfaceEmbedding, landmark_isomap
from reconstruct.errors import (
    CloudInPiecesError,
    DegenerateCloudError,
    InvalidInputError,
    ReconstructionWarning,
)
from reconstruct.neighbors import (
    choose_n_neighbors,
    classical_mds,
    farthest_point_sampling,
    knn_graph,
    landmark_residual_variance,
    largest_component,
    nearest_neighbors,
    residual_variance,
    smallest_connected_k,
)
from reconstruct.outliers import statistical_outlier_mask
from sim.shapes import make_shape


def plane(n=600, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 1, (n, 2)), np.zeros(n)])


def rigid_residual(embedding, truth):
    """RMS error after the best rotation/reflection + translation, *without* scaling."""
    a, b = embedding - embedding.mean(0), truth - truth.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    return float(np.sqrt(np.mean(np.sum((a @ u @ vt - b) ** 2, axis=1))))


@pytest.fixture(scope="module")
def s_curve():
    return make_shape("s_curve", 1000, noise=0.0, random_state=0)


# -- outliers ---------------------------------------------------------------------------------


def test_outlier_mask_removes_exactly_the_gross_outliers():
    surface = plane(1000)
    rng = np.random.default_rng(1)
    outliers = np.column_stack([rng.uniform(0, 1, (10, 2)), rng.uniform(0.5, 1.0, 10)])
    keep = statistical_outlier_mask(np.vstack([surface, outliers]), min_ratio=2.5)
    assert keep[:1000].all() and not keep[1000:].any()
    # Open3D's rule alone (min_ratio=0) also drops them, plus a few sparse boundary points.
    open3d_rule = statistical_outlier_mask(np.vstack([surface, outliers]))
    assert not open3d_rule[1000:].any() and open3d_rule[:1000].mean() > 0.97


def test_outlier_mask_keeps_a_regular_grid():
    u, v = np.meshgrid(np.arange(12.0), np.arange(12.0))
    grid = np.column_stack([u.ravel(), v.ravel(), np.zeros(144)])
    assert statistical_outlier_mask(grid, min_ratio=2.5).all()
    far = np.vstack([grid, [[5.0, 5.0, 40.0]]])
    assert np.flatnonzero(~statistical_outlier_mask(far)).tolist() == [144]


# -- neighbours -------------------------------------------------------------------------------


def test_nearest_neighbors_excludes_self_and_keeps_duplicates():
    points = np.vstack([plane(50), plane(50)[:5]])  # 50..54 duplicate 0..4
    distances, indices = nearest_neighbors(points, 6)
    assert indices.shape == (55, 6)
    assert not (indices == np.arange(55)[:, None]).any()
    for i in range(5):
        assert indices[i, 0] == 50 + i and distances[i, 0] == 0.0
        assert indices[50 + i, 0] == i
    graph = knn_graph(distances, indices)
    assert (graph != graph.T).nnz == 0  # symmetric
    assert graph[0, 50] > 0  # the zero-length edge is kept (tiny positive weight)
    assert graph[0, 50] < 1e-9


def test_components_and_smallest_connected_k():
    two = np.vstack([plane(300), plane(200, seed=1) + [3.0, 0, 0]])
    distances, indices = nearest_neighbors(two, 40)
    mask, n_pieces = largest_component(knn_graph(distances, indices, 10))
    assert n_pieces == 2 and mask[:300].all() and not mask[300:].any()
    # A single piece: the smallest K whose graph is connected, checked by brute force.
    distances, indices = nearest_neighbors(plane(300), 40)
    k = smallest_connected_k(distances, indices, 1, 20)
    assert largest_component(knn_graph(distances, indices, k))[1] == 1
    assert k == 1 or largest_component(knn_graph(distances, indices, k - 1))[1] > 1


def test_farthest_point_sampling_spreads_out():
    x = np.linspace(0, 1, 101)
    line = np.column_stack([x, np.zeros(101), np.zeros(101)])
    for seed in range(5):
        chosen = farthest_point_sampling(line, 5, random_state=seed)
        assert len(set(chosen.tolist())) == 5
        assert chosen[1] in (0, 100) and abs(x[chosen[1]] - x[chosen[0]]) >= 0.5
        # Max-min sampling is a 2-approximation of the best covering (radius 0.1 for 5 points).
        cover = np.abs(x[:, None] - x[chosen][None]).min(axis=1).max()
        assert cover <= 0.2 + 1e-12


def test_classical_mds_recovers_a_planar_configuration():
    rng = np.random.default_rng(3)
    truth = rng.uniform(-1, 1, (30, 2))
    squared = np.sum((truth[:, None] - truth[None]) ** 2, axis=-1)
    coords, values, _ = classical_mds(squared)
    assert rigid_residual(coords, truth) < 1e-10
    assert values[0] >= values[1] > 0
    assert residual_variance(squared, squared) == pytest.approx(0.0, abs=1e-12)


def test_k_choice_avoids_short_circuits():
    """S-curve of 300 points: K = 30 jumps between the folds; the residual variance sees it."""
    shape = make_shape("s_curve", 300, noise=0.0, random_state=0)
    distances, indices = nearest_neighbors(shape.points, 40)
    choice = choose_n_neighbors(
        shape.points, distances, indices, k_min=10, k_max=10, random_state=0
    )
    assert choice.candidates == (10, 15, 20, 30, 40)
    scores = dict(zip(choice.candidates, choice.residual_variances, strict=True))
    assert scores[30] > 10 * scores[20] and scores[40] > 10 * scores[20]
    assert choice.n_neighbors <= 20
    landmarks = farthest_point_sampling(shape.points, 32, random_state=0)
    graph = knn_graph(distances, indices, 30)
    assert landmark_residual_variance(graph, landmarks) == pytest.approx(scores[30], rel=1e-9)


# -- embedding --------------------------------------------------------------------------------


def test_isomap_unrolls_the_s_curve_isometrically(s_curve):
    model = SurfaceEmbedding(method="isomap").fit(s_curve.points)
    assert model.method_ == "isomap" and model.support_.all()
    assert model.embedding_.shape == (1000, 2) and model.embedding_.dtype == np.float64
    # Isomap preserves geodesic distances: same size as the (t, height) sheet, no rescaling.
    extent = np.sqrt(3 * np.pi * 2.0)
    assert rigid_residual(model.embedding_, s_curve.params) < 0.03 * extent
    assert model.residual_variance_ < 1e-3
    assert 5 <= model.n_neighbors_ <= 40


def test_landmark_isomap_matches_full_isomap(s_curve):
    full = SurfaceEmbedding(method="isomap", n_neighbors=12).fit(s_curve.points)
    landmark = SurfaceEmbedding(method="landmark", n_neighbors=12, n_landmarks=60).fit(
        s_curve.points
    )
    assert landmark.method_ == "landmark" and len(landmark.landmarks_) == 60
    assert procrustes(full.embedding_, landmark.embedding_)[2] < 1e-3
    assert rigid_residual(landmark.embedding_, s_curve.params) < 0.03 * np.sqrt(6 * np.pi)


def test_landmark_triangulation_reproduces_the_landmarks():
    points = plane(400)
    distances, indices = nearest_neighbors(points, 8)
    graph = knn_graph(distances, indices)
    embedding, landmarks, geodesic = landmark_isomap(graph, 25, np.random.default_rng(0))
    assert geodesic.shape == (25, 400) and len(set(landmarks.tolist())) == 25
    np.testing.assert_allclose(geodesic[np.arange(25), landmarks], 0.0)
    coords = classical_mds(geodesic[:, landmarks] ** 2)[0]
    np.testing.assert_allclose(embedding[landmarks], coords, atol=1e-9)


def test_landmark_isomap_gives_the_same_bits_whatever_the_blas_threads():
    from threadpoolctl import threadpool_limits

    points = make_shape("s_curve", 6000, noise=0.01, random_state=0).points
    distances, indices = nearest_neighbors(points, 10)
    graph = knn_graph(distances, indices)
    embedded = []
    for threads in (1, 2):
        with threadpool_limits(limits=threads):
            embedded.append(landmark_isomap(graph, 250, np.random.default_rng(0))[0])
    np.testing.assert_array_equal(*embedded)


def test_auto_picks_the_method_by_cloud_size():
    sparse = SurfaceEmbedding().fit(make_shape("sparse_cone").points)  # 36 points
    assert sparse.method_ == "mlle" and sparse.n_neighbors_ >= 6
    assert sparse.embedding_.shape == (36, 2) and np.isfinite(sparse.embedding_).all()
    assert SurfaceEmbedding().fit(make_shape("dense_cone").points).method_ == "isomap"
    big = SurfaceEmbedding().fit(make_shape("saddle", 3500, noise=0.005, random_state=0).points)
    assert big.method_ == "landmark"


def test_modified_lle_embeds_a_noisy_patch():
    shape = make_shape("saddle", 300, noise=0.005, random_state=0)
    model = SurfaceEmbedding(method="mlle", n_neighbors=12).fit(shape.points)
    assert model.method_ == "mlle" and model.n_neighbors_ == 12
    assert procrustes(shape.params[model.support_], model.embedding_)[2] < 0.02
    # Scaled to geodesic units: the same size as Isomap's embedding (RMS radius within 10 %).
    isomap = SurfaceEmbedding(method="isomap", n_neighbors=12).fit(shape.points).embedding_

    def rms_radius(y):
        return np.sqrt(np.mean(np.sum((y - y.mean(axis=0)) ** 2, axis=1)))

    assert rms_radius(model.embedding_) == pytest.approx(rms_radius(isomap), rel=0.1)


def test_user_k_overrides_and_same_seed_same_result(s_curve):
    a = SurfaceEmbedding(method="landmark", n_neighbors=7, random_state=4).fit(s_curve.points)
    b = SurfaceEmbedding(method="landmark", n_neighbors=7, random_state=4).fit(s_curve.points)
    assert a.n_neighbors_ == 7
    np.testing.assert_array_equal(a.embedding_, b.embedding_)
    assert clone(a).get_params()["n_neighbors"] == 7


def test_gross_outliers_are_dropped_from_the_support():
    surface = plane(800)
    spikes = np.array([[0.5, 0.5, 2.0], [0.2, 0.8, -1.5], [0.9, 0.1, 3.0]])
    model = SurfaceEmbedding().fit(np.vstack([surface, spikes]))
    assert model.support_[:800].all() and not model.support_[800:].any()
    assert model.embedding_.shape == (800, 2)
    assert procrustes(surface[:, :2], model.embedding_)[2] < 1e-3


def test_exact_duplicates_do_not_crash():
    points = np.vstack([plane(500), plane(500)[:40]])
    for method in ("isomap", "landmark", "mlle"):
        model = SurfaceEmbedding(method=method, n_neighbors=10).fit(points)
        assert model.support_.all() and np.isfinite(model.embedding_).all()
        if method != "mlle":  # same geodesic distances give the same coordinates
            np.testing.assert_allclose(model.embedding_[500:], model.embedding_[:40], atol=1e-9)


def test_graph_in_pieces(caplog):
    big, small = plane(700), plane(300, seed=1) + [4.0, 0.0, 0.0]
    with pytest.warns(ReconstructionWarning, match=r"2 pieces; reconstructing the largest \(700"):
        model = SurfaceEmbedding(method="isomap").fit(np.vstack([big, small]))
    assert model.support_[:700].all() and not model.support_[700:].any()
    assert model.inliers_[700:].mean() > 0.95  # no outliers: a mesh must account for them
    with pytest.raises(DegenerateCloudError, match="pieces"):
        pieces = [plane(400), plane(350, seed=2) + [4.0, 0, 0], plane(250, seed=3) + [0, 4.0, 0]]
        SurfaceEmbedding().fit(np.vstack(pieces))
    # how much the other pieces may hold is a parameter (an atlas may take the cloud instead)
    with pytest.raises(CloudInPiecesError, match="2 pieces; the largest holds 700") as caught:
        SurfaceEmbedding(method="isomap", other_pieces=0.2).fit(np.vstack([big, small]))
    sizes = caught.value.sizes  # largest first (2 outliers of the small piece dropped)
    assert len(sizes) == 2 and sizes[0] == 700 and 290 < sizes[1] <= 300


def test_degenerate_and_bad_input():
    line = np.column_stack([np.linspace(0, 1, 50)] * 3)
    with pytest.raises(DegenerateCloudError, match="collinear"):
        SurfaceEmbedding().fit(line)
    with pytest.raises(InvalidInputError, match="needs at least 8"):
        SurfaceEmbedding().fit(plane(5))
    with pytest.raises(InvalidInputError, match="needs at least 31"):
        SurfaceEmbedding(method="isomap", n_neighbors=30).fit(plane(20))
    with pytest.raises(InvalidInputError, match="unknown embedding method"):
        SurfaceEmbedding(method="tsne").fit(plane(50))
    with pytest.raises(InvalidInputError, match="n_neighbors >= 3"):
        SurfaceEmbedding(method="mlle", n_neighbors=2).fit(plane(50))
    with pytest.raises(InvalidInputError, match=r"\(n, 3\)"):
        SurfaceEmbedding().fit(np.zeros((50, 2)))
    with pytest.raises(InvalidInputError, match="method='landmark'"):
        SurfaceEmbedding(method="isomap").fit(plane(10_001))


def test_logs_progress(caplog):
    with caplog.at_level(logging.INFO, logger="reconstruct.embedding"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            SurfaceEmbedding(method="landmark", n_landmarks=40).fit(plane(500))
    assert "embedding 500 points: landmark Isomap, K=" in caplog.text
    assert "40 landmarks" in caplog.text
