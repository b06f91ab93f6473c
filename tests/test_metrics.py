"""Surface metrics (reconstruct.metrics) against answers known in closed form."""

import numpy as np
import pytest
import trimesh

from reconstruct.errors import InvalidInputError
from reconstruct.metrics import (
    accuracy,
    chamfer_l1,
    completeness,
    default_tau,
    denoise_ratio,
    distance_to_surface,
    fscore,
    paired_mse,
    precision_recall,
    sample_surface,
    surface_report,
)


def square(x0=0.0, x1=1.0, z=0.0, n=1):
    """The rectangle [x0, x1] x [0, 1] at height z as a grid mesh of 2 n^2 triangles."""
    u, v = np.meshgrid(np.linspace(x0, x1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    vertices = np.column_stack([u.ravel(), v.ravel(), np.full(u.size, z)])
    corner = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None]).ravel()
    faces = np.concatenate(
        [
            np.column_stack([corner, corner + n + 1, corner + 1]),
            np.column_stack([corner + 1, corner + n + 1, corner + n + 2]),
        ]
    )
    return trimesh.Trimesh(vertices, faces, process=False)


REFERENCE = square(n=40)


def test_points_above_a_plane_have_accuracy_h():
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(0, 1, (500, 2)), np.full(500, 0.03)])
    assert accuracy(points, REFERENCE) == pytest.approx(0.03, abs=1e-12)
    np.testing.assert_allclose(distance_to_surface(REFERENCE, points), 0.03, atol=1e-12)


def test_distances_are_exact_against_brute_force():
    # Small faces plus one huge one: sizes that differ by 100x must not break exactness.
    huge = trimesh.Trimesh([[3, 3, 3], [10, 3, 3], [3, 10, 3]], [[0, 1, 2]], process=False)
    mesh = trimesh.util.concatenate([trimesh.creation.icosphere(subdivisions=3), huge])
    rng = np.random.default_rng(1)
    # Near and far points: far ones need more than the first candidate triangles.
    points = rng.normal(size=(400, 3)) * rng.choice([0.2, 1.0, 5.0], size=(400, 1))
    brute = np.array(
        [
            np.linalg.norm(
                trimesh.triangles.closest_point(
                    mesh.triangles, np.repeat(p[None], len(mesh.faces), 0)
                )
                - p,
                axis=1,
            ).min()
            for p in points
        ]
    )
    np.testing.assert_allclose(distance_to_surface(mesh, points), brute, rtol=0, atol=1e-12)


def test_identical_meshes_score_perfectly():
    report = surface_report(REFERENCE, REFERENCE.vertices + [0, 0, 0.01], REFERENCE)
    assert report["accuracy"] == pytest.approx(0.0, abs=1e-12)
    assert report["completeness"] == pytest.approx(0.0, abs=1e-12)
    assert report["chamfer_l1"] == pytest.approx(0.0, abs=1e-12)
    assert report["fscore"] == report["precision"] == report["recall"] == 1.0
    assert report["denoise_ratio"] == pytest.approx(0.0, abs=1e-12)
    assert report["input_rms"] == pytest.approx(0.01)
    # A noise-free input has nothing to denoise: the ratio is undefined.
    assert np.isnan(denoise_ratio(REFERENCE, REFERENCE.vertices, REFERENCE))


def test_offset_mesh_and_threshold():
    lifted = square(z=0.02, n=3)
    assert chamfer_l1(lifted, REFERENCE) == pytest.approx(0.02, abs=1e-12)
    assert fscore(lifted, REFERENCE, tau=0.025) == 1.0
    assert fscore(lifted, REFERENCE, tau=0.015) == 0.0
    assert default_tau(REFERENCE) == pytest.approx(0.01 * np.sqrt(2))


def test_half_covering_mesh():
    half = square(0.0, 0.5, n=20)
    precision, recall = precision_recall(half, REFERENCE, tau=1e-6)
    assert precision == 1.0
    assert recall == pytest.approx(0.5, abs=0.015)
    # Reference samples over x in [0.5, 1] are (x - 0.5) from the half: mean 0.5 * 0.25.
    assert completeness(REFERENCE, half) == pytest.approx(0.125, abs=0.003)
    assert accuracy(half, REFERENCE) == pytest.approx(0.0, abs=1e-12)


def test_completeness_against_a_point_cloud():
    points = np.column_stack([np.full(2, 0.5), np.full(2, 0.5), [0.0, 0.0]])
    # Distance of uniform reference samples to the square's centre: mean ≈ 0.3826.
    assert completeness(REFERENCE, points) == pytest.approx(0.3826, abs=0.004)


def test_denoise_ratio_is_the_rms_ratio():
    rng = np.random.default_rng(2)
    sign = rng.choice([-1.0, 1.0], size=300)
    noisy = np.column_stack([rng.uniform(0.1, 0.9, (300, 2)), 0.05 * sign])  # RMS 0.05 exactly
    assert denoise_ratio(REFERENCE, noisy, REFERENCE) == pytest.approx(0.0, abs=1e-12)
    assert denoise_ratio(square(z=0.01), noisy, REFERENCE) == pytest.approx(0.2, abs=1e-12)


def test_paired_mse_is_per_point_squared_euclidean():
    clean = np.zeros((10, 3))
    assert paired_mse(clean + [1.0, 2.0, 2.0], clean) == pytest.approx(9.0)
    with pytest.raises(InvalidInputError, match="shape"):
        paired_mse(np.zeros((4, 3)), np.zeros((5, 3)))


def test_surface_report_matches_the_single_functions():
    lifted = square(z=0.004, n=5)
    noisy = REFERENCE.vertices + [0.0, 0.0, 0.01]
    report = surface_report(lifted, noisy, REFERENCE)
    assert report["accuracy"] == pytest.approx(accuracy(lifted, REFERENCE))
    assert report["completeness"] == pytest.approx(completeness(REFERENCE, lifted))
    assert report["fscore"] == pytest.approx(fscore(lifted, REFERENCE))
    assert report["denoise_ratio"] == pytest.approx(denoise_ratio(lifted, noisy, REFERENCE))
    assert report["denoise_ratio"] == pytest.approx(0.4, abs=1e-12)
    assert all(isinstance(value, float) for value in report.values())


def test_sampling_is_area_uniform_and_seeded():
    # Two triangles with areas 1 : 3 side by side.
    mesh = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, 2, 0], [1, 0, 0], [4, 0, 0], [1, 2, 0]],
        [[0, 1, 2], [3, 4, 5]],
        process=False,
    )
    samples = sample_surface(mesh, 40_000, random_state=5)
    assert np.mean(samples[:, 0] >= 1.0) == pytest.approx(0.75, abs=0.01)
    np.testing.assert_allclose(distance_to_surface(mesh, samples), 0.0, atol=1e-12)
    np.testing.assert_array_equal(samples, sample_surface(mesh, 40_000, random_state=5))


def test_bad_input():
    with pytest.raises(InvalidInputError, match="no faces"):
        accuracy(REFERENCE, trimesh.Trimesh())
    with pytest.raises(InvalidInputError, match=r"\(n, 3\)"):
        accuracy(np.zeros((5, 2)), REFERENCE)


@pytest.mark.parametrize("scale", [1e-6, 1e-4, 1.0, 1e4])
def test_distances_do_not_depend_on_the_unit(scale):
    # trimesh's closest point has absolute tolerances: a micrometre sphere's precision against
    # a finer one was 0.77 (1e-4) and 0.18 (1e-6)
    coarse, fine = trimesh.creation.icosphere(3, scale), trimesh.creation.icosphere(4, scale)
    assert precision_recall(fine, coarse) == (1.0, 1.0)
    points = np.random.default_rng(0).normal(size=(200, 3))
    at_unit = distance_to_surface(trimesh.creation.icosphere(3, 1.0), points)
    np.testing.assert_allclose(distance_to_surface(coarse, points * scale) / scale, at_unit,
                               rtol=1e-9, atol=1e-12)
