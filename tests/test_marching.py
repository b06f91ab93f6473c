"""The closed join's marching cubes, marched again only round what changed
(`reconstruct.marching.KeptMarch`): always skimage's march of the whole grid, bit for bit."""

import numpy as np
from skimage.measure import marching_cubes

from reconstruct.marching import KeptMarch, marched


def whole(values, voxel):
    vertices, faces, _, _ = marching_cubes(values, level=0.0, spacing=(voxel,) * 3,
                                           gradient_direction="ascent", allow_degenerate=False)
    return vertices, faces


def sphere(shape=(40, 44, 48), radius=14.3):
    z, y, x = np.meshgrid(*(np.arange(n) - n / 2 for n in shape), indexing="ij")
    return np.sqrt(x**2 + y**2 + z**2) - radius


def test_a_kept_march_is_the_whole_march_through_local_changes():
    rng = np.random.default_rng(0)
    values = sphere() + rng.normal(0, 1.0, (40, 44, 48))  # rough: ambiguous cells, centre vertices
    march, voxel = KeptMarch(), 0.37
    local = 0
    for step in range(12):
        if step:
            values = values.copy()
            corner = rng.integers(0, [34, 38, 42])
            size = rng.integers(1, 7, 3)
            box = tuple(slice(int(a), int(a + b)) for a, b in zip(corner, size, strict=True))
            values[box] += rng.normal(0, 1.0, values[box].shape)  # bumps, holes, new bits
        if step == 6:
            values[0:30, 0:30, 0:30] = 5.0  # a change over a large part: the whole grid again
        vertices, faces = march(values, voxel)
        expected_vertices, expected_faces = whole(values, voxel)
        assert vertices.dtype == expected_vertices.dtype == np.float32
        np.testing.assert_array_equal(vertices, expected_vertices)
        np.testing.assert_array_equal(faces, expected_faces)
        local += not march.whole_
    assert local >= 8  # most steps followed the kept march


def test_a_change_that_removes_the_surface_in_its_box_and_an_unchanged_grid():
    values = sphere()
    march = KeptMarch()
    march(values, 1.0)
    inside = values.copy()
    inside[18:24, 20:26, 4:12] = -3.0  # the sphere's wall there is gone: no surface in the box
    for grid in (inside, inside, values):
        vertices, faces = march(grid, 1.0)
        expected_vertices, expected_faces = whole(grid, 1.0)
        np.testing.assert_array_equal(vertices, expected_vertices)
        np.testing.assert_array_equal(faces, expected_faces)
        assert not march.whole_


def test_values_on_the_level_march_the_whole_grid_as_skimage_does():
    values = sphere()
    values[np.abs(values) < 0.5] = 0.0  # vertices on nodes, which several edges share
    march = KeptMarch()
    for grid in (values, values + 0.0, np.where(values == 0.0, 1e-9, values)):
        vertices, faces = march(grid, 0.5)
        expected_vertices, expected_faces = whole(grid, 0.5)
        np.testing.assert_array_equal(vertices, expected_vertices)
        np.testing.assert_array_equal(faces, expected_faces)


def test_changes_all_over_keep_only_the_grid_and_a_local_change_after_them_is_followed():
    rng = np.random.default_rng(1)
    values = sphere() + rng.normal(0, 0.3, (40, 44, 48))
    march = KeptMarch()
    steps = [values + rng.normal(0, 0.3, values.shape) for _ in range(3)]  # all over
    local = steps[-1].copy()
    local[10:14, 12:15, 20:23] += 0.8
    steps += [local, local + np.where(np.arange(48) == 30, 0.5, 0.0)]
    followed, kept = [], []
    for grid in steps:
        vertices, faces = march(grid, 0.5)
        expected_vertices, expected_faces = whole(grid, 0.5)
        np.testing.assert_array_equal(vertices, expected_vertices)
        np.testing.assert_array_equal(faces, expected_faces)
        followed.append(not march.whole_)
        kept.append("cells" in march._kept)  # what a march to follow needs
    assert kept == [True, False, False, True, True]
    assert followed == [False, False, False, False, True]


def test_a_float32_grid_changed_in_place_is_marched_again():
    """The closed grid is kept in float32, what skimage marches, and updated in place: the
    march keeps a copy to compare the next call's with, not the caller's array."""
    values = sphere().astype(np.float32)
    march = KeptMarch()
    march(values, 1.0)
    values[18:24, 20:26, 4:12] += 2.0  # a dent, in place
    vertices, faces = march(values, 1.0)
    expected_vertices, expected_faces = whole(values, 1.0)
    np.testing.assert_array_equal(vertices, expected_vertices)
    np.testing.assert_array_equal(faces, expected_faces)


def test_few_changes_far_apart_march_the_whole_grid():
    """Two small dents at opposite corners change few nodes, but their box is most of the grid:
    following the kept march there costs more than marching the crossed cells afresh."""
    values = sphere()
    march = KeptMarch()
    march(values, 1.0)
    apart = values.copy()
    apart[1:4, 1:4, 1:4] += 3.0
    apart[36:39, 40:43, 44:47] += 3.0
    near = apart.copy()
    near[10:12, 20:23, 4:7] -= 2.0
    followed = []
    for grid in (apart, near, near + np.where(np.arange(48) == 6, 0.25, 0.0)):
        vertices, faces = march(grid, 1.0)
        expected_vertices, expected_faces = whole(grid, 1.0)
        np.testing.assert_array_equal(vertices, expected_vertices)
        np.testing.assert_array_equal(faces, expected_faces)
        followed.append(not march.whole_)
    assert followed == [False, False, True]  # (the second keeps what the third follows)


def test_marching_the_crossed_cells_is_skimages_march():
    """`marched` scales a raw march of the cells the level crosses; skimage's own merges
    degenerate faces, and takes a grid with values on the level."""
    rng = np.random.default_rng(3)
    z, y, x = np.meshgrid(*(np.arange(n) - n / 2 for n in (30, 34, 38)), indexing="ij")
    rough = np.sqrt(x**2 + y**2 + z**2) - 11.3 + rng.normal(0, 0.7, x.shape)
    on_level = np.where(np.abs(rough) < 0.3, 0.0, rough)
    nearly = np.where(np.abs(rough) < 0.3, np.copysign(1e-9, rough), rough)  # corners merged
    mask = rng.random(rough.shape) < 0.9
    for values in (rough, on_level, nearly, rough.astype(np.float32)):
        for within in (None, mask):
            vertices, faces = marched(values, 0.43, within)
            expected, expected_faces, _, _ = marching_cubes(
                values, 0.0, spacing=(0.43,) * 3, mask=within, gradient_direction="ascent",
                allow_degenerate=False)
            assert vertices.dtype == expected.dtype == np.float32
            np.testing.assert_array_equal(vertices, expected)
            np.testing.assert_array_equal(faces, expected_faces)
