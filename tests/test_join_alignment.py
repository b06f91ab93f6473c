"""A closed join whose topology depends on where its grid falls: joined again on shifted
lattices, the most frequent topology is kept and the atlas says so (reconstruct.join_alignment)."""

import trimesh

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
    assert asked == list(SHIFTS[1:]) and "2 / 0 / 4" in note and "kept 2;" in note
