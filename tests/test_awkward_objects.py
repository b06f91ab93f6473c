"""The simulated station's non-star-shaped objects: closed, oriented, of their stated genus."""

import numpy as np
import pytest
import trimesh

from sim.awkward_objects import AWKWARD, GENUS, UNTUNED, sample_cloud
from sim.objects import load_object


def crossings_from_axis(mesh: trimesh.Trimesh, heights, n_angles=24) -> int:
    """The most surface crossings of a horizontal ray from the turntable axis."""
    phi = 2 * np.pi * np.arange(n_angles) / n_angles
    z = np.repeat(heights, n_angles)
    origins = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    directions = np.column_stack([np.tile(np.cos(phi), len(heights)),
                                  np.tile(np.sin(phi), len(heights)), np.zeros_like(z)])
    _, rays = mesh.ray.intersects_location(origins, directions, multiple_hits=True)[:2]
    return int(np.bincount(rays, minlength=len(origins)).max())


@pytest.mark.parametrize("name", sorted({**AWKWARD, **UNTUNED}))
def test_object_is_closed_oriented_and_of_its_genus(name):
    mesh = load_object(name)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert mesh.euler_number == 2 - 2 * GENUS[name]
    assert len(mesh.split(only_watertight=False)) == 1
    assert 100 < np.linalg.norm(mesh.extents) < 250  # about 150 mm, as on a scan station
    assert mesh.extents[2] <= 130 and mesh.extents[:2].max() < 200  # fits the plate and frame
    assert mesh.bounds[0, 2] == pytest.approx(0.0)


@pytest.mark.parametrize("name", sorted({**AWKWARD, **UNTUNED}))
def test_object_is_not_star_shaped_about_the_axis(name):
    mesh = load_object(name)
    heights = np.linspace(0.05, 0.95, 19) * mesh.bounds[1, 2]
    assert crossings_from_axis(mesh, heights) > 1


def test_the_vase_is_star_shaped_about_the_axis():
    mesh = load_object("vase")
    assert crossings_from_axis(mesh, np.linspace(5, 115, 12)) == 1


def test_sample_cloud_noise_is_a_share_of_the_diagonal():
    mesh = load_object("torus")
    clean = sample_cloud(mesh, 3000, 0.0, random_state=1)
    noisy = sample_cloud(mesh, 3000, 0.01, random_state=1)
    assert clean.shape == noisy.shape == (3000, 3)
    spread = np.std(noisy - clean)
    assert spread == pytest.approx(0.01 * np.linalg.norm(mesh.extents), rel=0.1)
    assert np.array_equal(sample_cloud(mesh, 100, 0.01, random_state=2),
                          sample_cloud(mesh, 100, 0.01, random_state=2))
