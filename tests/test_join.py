"""Joining charts into one mesh: which side is outside, a closed cloud closed across the gaps
between its charts, open data left open (reconstruct.join)."""

import numpy as np
import trimesh

from reconstruct.grid_steps import VOTERS, pocket_voters
from reconstruct.join import (
    ExteriorProbe,
    border_vertices,
    exterior_votes,
    faces_seen_side,
    implicit_mesh,
    kept_topology,
    stretched_samples,
    thin_shell,
)
from reconstruct.mesh_edges import (
    edge_runs,
    face_centres,
    kept_faces,
    split_nonmanifold,
    topology,
    turn_faces,
)
from reconstruct.sdf_grid import SparseSDF


def tube_samples(gap: float = 0.0, n: int = 6000, seed: int = 0):
    """Samples (m, 3) and outward normals of a thick-walled open tube (a mug without its
    floor: radii 1 and 0.8, height 2, genus 1) with no samples on its two rims and, beyond
    ``gap`` of the rim, none on the walls either (the gaps charts leave at sharp edges)."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, n)
    height = rng.uniform(gap, 2 - gap, n)
    radius = np.where(np.arange(n) % 2 == 0, 1.0, 0.8)
    radial = np.c_[np.cos(angle), np.sin(angle), np.zeros(n)]
    samples = radial * radius[:, None] + np.c_[0 * angle, 0 * angle, height]
    normals = radial * np.where(radius > 0.9, 1.0, -1.0)[:, None]
    return samples, normals


def test_a_closed_join_caps_the_gaps_between_charts():
    samples, normals = tube_samples(gap=0.08)
    voxel = 0.05
    mesh = implicit_mesh(samples, normals, voxel, closed=True)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.euler_number == 0  # one handle: the tube's wall closed round both rims
    assert mesh.volume > 0
    # the rims are capped near the data's ends, not at the band's edge
    assert mesh.vertices[:, 2].max() < 2 + 0.5 * 3 * voxel
    # the open join leaves both rims open
    assert not implicit_mesh(samples, normals, voxel).is_watertight


def test_exterior_votes_find_the_outside_of_each_chart():
    samples, normals = tube_samples()
    outer = samples[:, :2].__pow__(2).sum(axis=1) > 0.81
    charts = [samples[outer], samples[~outer]]
    votes, two_sided = exterior_votes(charts, [normals[outer], -normals[~outer]], 0.05)
    assert two_sided.max() < 0.1
    assert votes[0] > 0.8 and votes[1] < -0.8  # the inner wall's normals were flipped
    # a single open sheet is outside on both sides: no vote
    rng = np.random.default_rng(1)
    sheet = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    up = np.tile([0.0, 0.0, 1.0], (2000, 1))
    votes, two_sided = exterior_votes([sheet], [up], 0.05)
    assert abs(votes[0]) < 0.1 and two_sided[0] > 0.9


def test_data_no_chart_represents_closes_a_hole_in_the_samples_for_the_votes():
    # a sphere's samples with a cap left out (wider than twice the band) where the data lies:
    # through the hole the inside looks outside and the chart two-sided, unless that data
    # occupies the votes' grid (as it does a closed join's)
    rng = np.random.default_rng(3)
    direction = rng.normal(size=(20000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    cap = direction[:, 2] > 0.85
    charts, normals = [direction[~cap]], [direction[~cap]]
    votes, two_sided = exterior_votes(charts, normals, 0.05)
    assert two_sided[0] > 0.5
    votes, two_sided = exterior_votes(charts, normals, 0.05, extra=direction[cap])
    assert votes[0] > 0.9 and two_sided[0] < 0.05
    # a sheet's noisy data on both sides of it encloses nothing: the sheet stays two-sided
    sheet = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    up = np.tile([0.0, 0.0, 1.0], (2000, 1))
    noise = np.c_[rng.uniform(-1, 1, (4000, 2)), np.repeat([-0.1, 0.1], 2000)]
    votes, two_sided = exterior_votes([sheet], [up], 0.05, extra=noise)
    assert abs(votes[0]) < 0.1 and two_sided[0] > 0.9


def test_the_probe_finds_a_flap_turned_into_the_object():
    samples, normals = tube_samples()
    outer = (samples[:, :2] ** 2).sum(axis=1) > 0.81
    chart_normals = normals[outer].copy()
    flap = samples[outer][:, 0] > 0.95  # a folded chart's flap: its normals into the wall
    chart_normals[flap] *= -1
    probe = ExteriorProbe(samples, 0.05, 3.0)
    inward = probe.facing_in(samples[outer], chart_normals)
    assert inward[flap].mean() > 0.9 and not inward[~flap].any()
    assert not probe.facing_in(samples[~outer], normals[~outer]).any()


def test_a_sheet_joined_as_a_thin_shell_is_closed():
    rng = np.random.default_rng(2)
    direction = rng.normal(size=(4000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    cap = direction[direction[:, 2] > 0.3]  # an open cap of a sphere, sampled once
    samples, normals = thin_shell(cap, cap, 0.06)
    assert len(samples) == 2 * len(cap)
    mesh = implicit_mesh(samples, normals, 0.04, closed=True)
    assert mesh.is_watertight and mesh.euler_number == 2
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert 0.88 < radius.min() and radius.max() < 1.12


def test_a_gap_facing_kept_open_samples_stays_open():
    # two plates (square sheets 2 across at x = ±0.2, joined as shells 0.2 thick) with a gap of
    # 2 voxels between their facing faces: a closed join caps it (the opening fills voids under
    # 3 voxels) unless the faces towards it are kept open
    u = np.linspace(-1, 1, 61)
    grid = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
    samples, normals = [], []
    for x in (-0.2, 0.2):
        sheet = np.c_[np.full(len(grid), x), grid]
        s, n = thin_shell(sheet, np.tile([np.sign(x), 0.0, 0.0], (len(grid), 1)), 0.1)
        samples.append(s)
        normals.append(n)
    samples, normals = np.concatenate(samples), np.concatenate(normals)
    voxel = 0.1

    def in_gap(mesh):  # vertices of faces towards the gap, away from the plates' borders
        v = mesh.vertices
        return np.sum((np.abs(v[:, 0]) < 0.15) & (np.abs(v[:, 1:]) < 0.6).all(axis=1))

    capped = implicit_mesh(samples, normals, voxel, closed=True)
    opened = implicit_mesh(samples, normals, voxel, closed=True,
                           kept_open=np.ones(len(samples), bool))
    assert capped.is_watertight and opened.is_watertight
    assert in_gap(capped) == 0 and in_gap(opened) > 100
    assert opened.volume < 0.8 * capped.volume


def test_sheets_touching_along_an_edge_are_parted():
    a, b = trimesh.creation.box(), trimesh.creation.box()
    b.apply_translation((1, 1, 0))
    touching = trimesh.util.concatenate([a, b])
    touching.merge_vertices()
    assert not touching.is_watertight  # one edge in four faces
    parted = split_nonmanifold(touching)
    assert parted.is_watertight and parted.euler_number == 4
    assert len(parted.vertices) == len(touching.vertices) + 2
    sphere = trimesh.creation.icosphere(2)
    assert split_nonmanifold(sphere) is sphere


def test_solids_touching_at_a_corner_are_parted():
    # every edge in two faces, wound against each other: the cheap test of one fan a vertex
    # (mesh_edges._one_fan_each) must still find the corner where the two fans meet
    a, b = trimesh.creation.box(), trimesh.creation.box()
    b.apply_translation((1, 1, 1))
    touching = trimesh.util.concatenate([a, b])
    touching.merge_vertices()
    assert touching.is_watertight and touching.is_winding_consistent
    assert len(touching.vertices) == 15
    parted = split_nonmanifold(touching)
    assert len(parted.vertices) == 16 and parted.euler_number == 4
    assert np.array_equal(np.sort(parted.vertices, axis=0)[[0, -1]], [[-0.5] * 3, [1.5] * 3])


def test_data_no_chart_represents_keeps_a_closed_join_whole():
    # the tube's wall has no samples round its middle (z 0.8–1.2, wider than twice the band):
    # the join closes each half apart, unless the data points there occupy the gap
    samples, normals = tube_samples()
    middle = np.abs(samples[:, 2] - 1.0) < 0.2
    apart = implicit_mesh(samples[~middle], normals[~middle], 0.05, closed=True)
    whole = implicit_mesh(samples[~middle], normals[~middle], 0.05, closed=True,
                          uncharted=samples[middle])
    assert len(apart.split(only_watertight=False)) == 2
    assert whole.is_watertight and len(whole.split(only_watertight=False)) == 1
    assert whole.euler_number == 0



def test_a_large_pocket_votes_through_an_even_subset_of_its_nodes():
    rng = np.random.default_rng(0)
    shape = (64, 64, 64)
    flat = np.sort(rng.choice(np.prod(shape), 10 + 3 * VOTERS + 500 + 3, replace=False))
    label = rng.permutation(np.repeat([1, 2, 3], [10, 3 * VOTERS + 500, 3]))
    nodes, kept_label, kept = pocket_voters(flat, label, shape)
    counts = np.bincount(kept_label, minlength=4)
    assert counts[1] == 10 and counts[3] == 3  # small pockets: every node
    assert 0.9 < counts[2] / ((3 * VOTERS + 500) / 4) < 1.1  # every 4th, by a hash
    assert np.all(np.diff(kept) > 0)
    np.testing.assert_array_equal(label[np.searchsorted(flat, kept)], kept_label)
    np.testing.assert_array_equal(np.ravel_multi_index(tuple(nodes.T), shape), kept)
    # taken evenly across the grid, not whole rows or planes of it
    share = np.bincount(nodes[kept_label == 2, 2] % 4, minlength=4) / counts[2]
    assert np.all(np.abs(share - 0.25) < 0.05)
    # a voter stays one while its pocket changes elsewhere, by less than a step's worth of
    # VOTERS nodes (its vote is kept)
    others = rng.choice(np.flatnonzero(label == 2), 50, replace=False)
    _, _, again = pocket_voters(np.delete(flat, others), np.delete(label, others), shape)
    assert set(again) == set(kept) - set(flat[others])


def test_a_closed_join_leaves_no_void_inside_the_object():
    """Samples of a second, inward-facing layer under the surface (two layers of a shell's
    samples met) close a void of their own: nothing a scanner sees, so it is dropped."""
    outer = trimesh.creation.icosphere(4)
    inner = trimesh.creation.icosphere(3)
    inner.apply_scale(0.5)
    samples = np.concatenate([outer.vertices, inner.vertices])
    normals = np.concatenate([outer.vertex_normals, -inner.vertex_normals])
    mesh = implicit_mesh(samples, normals, voxel=0.05, closed=True)
    assert mesh.is_watertight and mesh.euler_number == 2 and mesh.volume > 0
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 1).max() < 0.05


def test_topology_reads_as_trimesh_does():
    sphere = trimesh.creation.icosphere(2)
    flipped = sphere.faces.copy()
    flipped[0] = flipped[0][::-1]
    fin = np.r_[sphere.faces, [[sphere.faces[0][0], sphere.faces[0][1], len(sphere.vertices)]]]
    meshes = [trimesh.creation.torus(1.0, 0.3), sphere,
              trimesh.Trimesh(sphere.vertices, sphere.faces[5:], process=False),  # holed
              trimesh.Trimesh(sphere.vertices, flipped, process=False),  # one face turned
              trimesh.Trimesh(np.r_[sphere.vertices, [[3.0, 0, 0]]], fin, process=False)]
    for mesh in meshes:  # the last has an edge of three faces
        assert topology(mesh.faces) == (mesh.is_watertight, mesh.is_winding_consistent,
                                         mesh.euler_number)
    assert topology(np.zeros((0, 3), int)) == (False, False, 0)


def test_kept_faces_drops_faces_and_vertices_and_keeps_the_edge_runs():
    # a sphere and a small box apart: dropping the box, or a cap of the sphere, gives the
    # mesh trimesh's update_faces and remove_unreferenced_vertices give, and its runs are
    # those edge_runs finds for it
    sphere = trimesh.creation.icosphere(subdivisions=2)
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    box.apply_translation((3.0, 0.0, 0.0))
    mesh = trimesh.util.concatenate([box, sphere])
    for keep in (np.arange(len(mesh.faces)) >= len(box.faces),
                 mesh.triangles_center[:, 2] < 0.5):
        expected = mesh.copy()
        expected.update_faces(keep)
        expected.remove_unreferenced_vertices()
        kept, runs = kept_faces(mesh, keep, edge_runs(np.asarray(mesh.faces)))
        np.testing.assert_array_equal(kept.vertices, expected.vertices)
        np.testing.assert_array_equal(kept.faces, expected.faces)
        for got, want in zip(runs, edge_runs(np.asarray(kept.faces)), strict=True):
            np.testing.assert_array_equal(got, want)
        assert kept_faces(mesh, keep)[1] is None


def test_face_centres_are_trimeshs_to_the_bit():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh.vertices = mesh.vertices * [1.0, 2.5, 0.3] + np.random.default_rng(0).normal(
        0, 0.01, mesh.vertices.shape)
    np.testing.assert_array_equal(face_centres(mesh.vertices, mesh.faces), mesh.triangles_center)
    flat = np.asarray(mesh.vertices)[:, :2]  # a chart's 2D mesh
    np.testing.assert_array_equal(face_centres(flat, mesh.faces), flat[mesh.faces].mean(axis=1))
    assert face_centres(np.zeros((0, 3)), np.zeros((0, 3), int)).shape == (0, 3)


def stretched_grid():
    """A chart's mesh on an 8 × 8 grid (u, v) whose map stretches 3 < u < 5 four times, the
    same grid level, and u."""
    from scipy.spatial import Delaunay

    u, v = np.mgrid[0:8, 0:8].reshape(2, -1).astype(float)
    faces = Delaunay(np.c_[u, v]).simplices
    x = u + 3 * np.clip(u - 3, 0, 2)
    return (trimesh.Trimesh(np.c_[x, v, np.sin(u)], faces, process=False),
            trimesh.Trimesh(np.c_[u, v, 0 * u], faces, process=False), u)


def assert_gap_filled(mesh, kept, extra, low, high):
    """Between x = ``low`` and ``high`` the kept vertices leave gaps over 1.3, and with the
    ``extra`` samples none."""
    from scipy.spatial import cKDTree

    probe = trimesh.sample.sample_surface(mesh, 4000, seed=0)[0]
    probe = probe[(probe[:, 0] > low) & (probe[:, 0] < high)]
    gap = cKDTree(np.concatenate([mesh.vertices[kept], extra])).query(probe)[0].max()
    assert gap < 1.3 < cKDTree(mesh.vertices[kept]).query(probe)[0].max()


def test_a_stretched_chart_is_filled_on_its_faces():
    mesh, level, u = stretched_grid()
    kept = np.flatnonzero(u < 6)  # the chart's own part
    normals = np.tile([0.0, 0.0, 1.0], (len(kept), 1))
    ((extra, extra_normals),) = stretched_samples([mesh], [kept], [normals], 2.0)
    assert len(extra) > 0
    assert (extra[:, 0] > 3 - 1e-9).all() and (extra[:, 0] < 11 + 1e-9).all()  # stretched, kept
    assert trimesh.proximity.closest_point(mesh, extra)[1].max() < 1e-9  # on the chart's faces
    np.testing.assert_allclose(extra_normals, np.tile([0.0, 0.0, 1.0], (len(extra), 1)))
    assert_gap_filled(mesh, kept, extra, 3, 11)
    both = stretched_samples([level, mesh], [kept, kept], [normals, normals], 2.0)
    assert len(both[0][0]) == 0  # sides of 1 and diagonals of 1.4: nothing to fill
    np.testing.assert_array_equal(both[1][0], extra)  # each chart by its own median


def test_a_face_across_the_border_between_two_parts_is_filled():
    mesh, level, u = stretched_grid()
    kept = np.flatnonzero(u < 4)  # the border between two parts crosses the stretched band
    normals = np.tile([0.0, 0.0, 1.0], (len(kept), 1))
    border = border_vertices(mesh, kept)
    np.testing.assert_array_equal(border, np.flatnonzero(u == 4))
    ((alone, _),) = stretched_samples([mesh], [kept], [normals], 2.0)
    assert len(alone) == 0  # a border not shared (a hole's rim, the data's edge) stays
    ((extra, extra_normals),) = stretched_samples([mesh], [kept], [normals], 2.0, [border])
    # the kept vertices stop 4 short of the next node (x = 3 -> 7): the faces across are
    # filled as far as that node, with the kept corners' normals, none beyond
    assert len(extra) > 0
    assert (extra[:, 0] > 3 + 1e-9).all() and (extra[:, 0] < 7 - 1e-9).all()
    np.testing.assert_allclose(extra_normals, np.tile([0.0, 0.0, 1.0], (len(extra), 1)))
    assert_gap_filled(mesh, kept, extra, 3, 4.5)
    ((flat, _),) = stretched_samples([level], [kept], [normals], 2.0, [border])
    # unstretched: only the diagonals across (1.4 edges) get a sample, at their midpoints
    np.testing.assert_allclose(flat[:, :2], np.c_[np.full(7, 3.5), np.arange(7) + 0.5])


def test_an_open_join_faces_the_side_it_was_seen_from():
    x, y = np.meshgrid(np.linspace(-50, 50, 41), np.linspace(-50, 50, 41))
    z = 6 * np.sin(x / 9) * np.cos(y / 13)  # a relief, seen from above
    corner = (np.arange(40)[:, None] * 41 + np.arange(40)).ravel()
    quads = np.c_[corner, corner + 1, corner + 42, corner + 41]
    relief = trimesh.Trimesh(np.c_[x.ravel(), y.ravel(), z.ravel()],
                             np.r_[quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], process=False)
    tube = trimesh.creation.revolve(np.array([(40.0, 60.0), (40.0, 0.0)]), sections=48)
    for mesh, out in ((relief, lambda m: m.face_normals[:, 2]),  # up
                      (tube, lambda m: np.einsum("ij,ij->i", m.face_normals[:, :2],
                                                 m.triangles_center[:, :2]))):  # radially out
        points = mesh.vertices
        for turned in (mesh.copy(), turn_faces(mesh.copy())):  # either way round to begin
            if not faces_seen_side(turned.vertices, turned.faces, points, up=(0, 0, 1)):
                turn_faces(turned)
            assert (out(turned) > 0).all()
            assert (out(trimesh.Trimesh(turned.vertices, turned.faces, process=False)) > 0).all()
    assert not faces_seen_side(relief.vertices, relief.faces, relief.vertices, up=(0, 0, -1))


def test_turned_faces_have_turned_normals():
    sphere = trimesh.creation.icosphere(1)
    before = sphere.face_normals.copy()  # cached: trimesh's invert would keep these
    turn_faces(sphere)
    np.testing.assert_allclose(sphere.face_normals, -before, atol=1e-12)
    assert sphere.volume < 0


def test_an_open_join_whose_faces_are_all_far_from_the_data_is_empty():
    # every face trimmed: an empty mesh, not an error (np.max of no pieces raised)
    rng = np.random.default_rng(0)
    xy = rng.random((2000, 2))
    samples = np.c_[xy, np.zeros(len(xy))]
    normals = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    mesh = implicit_mesh(samples, normals, voxel=0.05, data=np.full((5, 3), 50.0))
    assert len(mesh.faces) == 0


def test_a_grid_knows_the_topology_of_its_mesh_turned_over_and_no_other():
    rng = np.random.default_rng(2)
    xy = rng.random((3000, 2))
    samples = np.c_[xy, 0.1 * np.sin(4 * xy[:, 0])]
    normals = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    grid = SparseSDF(0.04)
    mesh = implicit_mesh(samples, normals, voxel=0.04, grid=grid)
    faces = np.asarray(mesh.faces)
    assert kept_topology(grid, faces) == topology(faces)
    assert kept_topology(grid, faces[:, ::-1]) == topology(faces[:, ::-1])  # turned over
    assert kept_topology(grid, faces[1:]) is None
