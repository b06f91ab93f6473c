"""A closed join whose topology depends on where its grid falls: joined again on shifted
lattices, the most frequent topology is kept and the atlas says so (reconstruct.join_alignment)."""

import pytest
import trimesh
from surface_checks import sphere_cloud

import reconstruct.atlas as atlas_module
from reconstruct.atlas import AtlasReconstructor
from reconstruct.errors import ReconstructionWarning
from reconstruct.join_alignment import SHIFTS, steady_join

SPHERE = trimesh.creation.icosphere(2)  # Euler characteristic 2
TORUS = trimesh.creation.torus(1.0, 0.3, major_sections=24, minor_sections=12)  # 0


def joins(*meshes):
    """A ``join(shift)`` giving ``meshes`` in turn, and the shifts it was asked for."""
    asked = []

    def join(shift):
        asked.append(shift)
        return meshes[len(asked) - 1], f"grid {shift}"
    return join, asked


def test_two_joins_that_agree_keep_the_first_and_say_nothing():
    join, asked = joins(trimesh.Trimesh(SPHERE.vertices * 1.01, SPHERE.faces))
    mesh, grid, facts, note = steady_join(SPHERE, "grid 0", join)
    assert mesh is SPHERE and grid == "grid 0" and facts == (True, True, 2) and note is None
    assert asked == [SHIFTS[1]]


def test_the_most_frequent_topology_is_kept_and_said():
    join, asked = joins(SPHERE, SPHERE)
    mesh, grid, facts, note = steady_join(TORUS, "grid 0", join)
    assert asked == list(SHIFTS[1:]) and mesh is SPHERE and grid == f"grid {SHIFTS[1]}"
    assert facts[2] == 2 and "0 / 2 / 2" in note and "kept 2 (the most frequent)" in note


def test_three_different_topologies_keep_the_unshifted_join():
    two = trimesh.util.concatenate([SPHERE, SPHERE.copy().apply_translation([5, 0, 0])])  # 4
    join, asked = joins(TORUS, two)
    mesh, grid, facts, note = steady_join(SPHERE, "grid 0", join)
    assert mesh is SPHERE and grid == "grid 0" and facts[2] == 2
    assert asked == list(SHIFTS[1:]) and "2 / 0 / 4" in note and note.endswith("kept 2")


def test_an_unsteady_atlas_join_advises_a_larger_voxel_than_its_own(monkeypatch):
    def unsteady(mesh, grid, join):
        return mesh, grid, (True, True, 2), "the closed mesh's topology depends on (...)"
    monkeypatch.setattr(atlas_module, "steady_join", unsteady)
    with pytest.warns(ReconstructionWarning, match=r"topology depends .* a larger voxel may "
                      r"steady it \(voxel=0\.84, --voxel 0\.84; now 0\.6 median spacings\)"):
        AtlasReconstructor(voxel=0.6, n_jobs=1).fit(sphere_cloud())
