"""Closed objects as trimmed patches: full coverage, one layer at every seam, seams zipped."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import Delaunay, cKDTree
from sklearn.base import BaseEstimator
from surface_checks import hits_per_ray, side_rays

from reconstruct.errors import InvalidInputError
from reconstruct.patches import PatchReconstructor, zip_seam
from reconstruct.pipeline import SurfaceReconstructor


def vase(top: bool = True) -> trimesh.Trimesh:
    """A bulging surface of revolution, 135 mm tall, open at the bottom, domed top if ``top``."""
    z = np.linspace(0, 120, 61)
    profile = np.c_[40 + 12 * np.sin(np.pi * z / 150), z]
    if top:
        t = np.linspace(0, np.pi / 2, 25)[1:]
        profile = np.r_[profile, np.c_[profile[-1, 0] * np.cos(t), 120 + 15 * np.sin(t)]]
    return trimesh.creation.revolve(profile, sections=128)


def sample(mesh, n=11000, noise=0.15, seed=0):
    """(n, 3) points on ``mesh`` moved by Gaussian noise along the normals, mm."""
    points, faces = trimesh.sample.sample_surface_even(mesh, n, seed=seed)
    rng = np.random.default_rng(seed)
    return points + mesh.face_normals[faces] * rng.normal(0, noise, (len(points), 1))


class DirectionDelaunay(BaseEstimator):
    """Cheap stand-in reconstructor for star-shaped patches: Delaunay of the points' directions
    seen from a centre on the axis (azimuthal projection about the mean direction); the points
    are the vertices."""

    def __init__(self, centre_z=60.0):
        self.centre_z = centre_z

    def fit(self, points):
        d = points - [0, 0, self.centre_z]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        m = d.mean(axis=0) / np.linalg.norm(d.mean(axis=0))
        e1 = np.cross(m, [0.3, 0.5, 0.8])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(m, e1)
        angle = np.arccos(np.clip(d @ m, -1, 1))
        uv = angle[:, None] * np.c_[d @ e1, d @ e2] / np.maximum(np.sin(angle), 1e-9)[:, None]
        faces = Delaunay(uv).simplices
        spacing = np.median(cKDTree(points).query(points, k=2)[0][:, 1])
        edges = np.linalg.norm(points[faces] - points[faces][:, [1, 2, 0]], axis=2)
        self.mesh_ = trimesh.Trimesh(points, faces[edges.max(axis=1) < 5 * spacing], process=False)
        return self


def capped_cylinder() -> trimesh.Trimesh:
    """Radius 40 mm, 110 mm tall, a flat top with a sharp rim, open at the bottom."""
    profile = np.r_[np.c_[np.full(56, 40.0), np.linspace(0, 110, 56)], [[20, 110], [0, 110]]]
    return trimesh.creation.revolve(profile, sections=128)


def elliptic_vase() -> trimesh.Trimesh:
    """The vase squeezed to an elliptic section and standing 6 mm off the axis."""
    mesh = vase()
    mesh.apply_transform(np.diag([1.25, 0.9, 1.0, 1.0]))
    return mesh.apply_translation([6.0, -4.0, 0.0])


OBJECTS = {"vase": vase, "elliptic": elliptic_vase, "cylinder": capped_cylinder}


@pytest.fixture(scope="module", params=list(OBJECTS))
def closed_fit(request):
    truth = OBJECTS[request.param]()
    points = sample(truth)
    model = PatchReconstructor(reconstructor=DirectionDelaunay()).fit(points)
    return truth, points, model


def test_closed_top_gets_a_cap_and_all_patches(closed_fit):
    _, _, model = closed_fit
    top = model.mesh_.vertices[:, 2].max()
    assert model.has_cap_ and model.cap_height_ == pytest.approx(0.8 * top, abs=0.5)
    assert model.patch_names_[-1] == "cap" and len(model.patch_meshes_) == 7
    np.testing.assert_allclose(model.boundaries_deg_, np.arange(0, 360, 60))
    assert model.n_seam_faces_ > 0


def test_every_side_ray_crosses_the_merged_surface_once(closed_fit):
    _, _, model = closed_fit
    # Every 0.5°: the seams (0.1° = 0.09 mm beside them: a ray IN a seam plane runs along the
    # seam), the ±20° overlaps and the sector interiors alike.
    angles = np.r_[np.arange(0.1, 360, 0.5), np.arange(0, 360, 60) - 0.1]
    origins, directions = side_rays(np.linspace(6, model.cap_height_ - 4, 9), angles)
    hits = hits_per_ray(model.mesh_, origins, directions)
    assert np.all(hits == 1), f"{np.sum(hits != 1)} of {len(hits)} rays cross != 1 time"


def test_every_ray_through_the_cap_seam_crosses_once(closed_fit):
    _, _, model = closed_fit
    elevation, azimuth = np.meshgrid(
        np.radians(np.arange(15, 88, 6)),
        np.radians(np.r_[np.arange(0.1, 360, 3), np.arange(0, 360, 60) - 0.1]),
    )
    directions = np.c_[
        (np.cos(elevation) * np.cos(azimuth)).ravel(),
        (np.cos(elevation) * np.sin(azimuth)).ravel(),
        np.sin(elevation).ravel(),
    ]
    origins = np.tile([0.0, 0.0, model.cap_height_ - 15], (len(directions), 1))
    hits = hits_per_ray(model.mesh_, origins, directions)
    assert np.all(hits == 1), f"{np.sum(hits != 1)} of {len(hits)} rays cross != 1 time"


def test_untrimmed_patches_would_double_the_overlaps(closed_fit):
    """The ray test can fail: the overlapping patches before trimming cross twice."""
    _, points, _ = closed_fit
    phi = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    sectors = []
    for start in (0.0, 60.0):
        delta = (phi - start - 30 + 180) % 360 - 180
        mask = (np.abs(delta) <= 50) & (points[:, 2] < 120)
        sectors.append(DirectionDelaunay().fit(points[mask]).mesh_)
    both = trimesh.util.concatenate(sectors)
    hits = hits_per_ray(both, *side_rays([40.0, 70.0], np.arange(45, 75, 1.0)))
    assert np.all(hits == 2)


def test_area_and_coverage_match_the_true_surface(closed_fit):
    truth, _, model = closed_fit
    assert model.mesh_.area == pytest.approx(truth.area, rel=0.03)
    probe = trimesh.sample.sample_surface_even(truth, 3000, seed=1)[0]
    probe = probe[probe[:, 2] > 3]
    _, distance, _ = trimesh.proximity.closest_point(model.mesh_, probe)
    assert distance.max() < 1.0


def test_seams_are_closed_only_the_bottom_rim_stays_open(closed_fit):
    truth, _, model = closed_fit
    mesh = model.mesh_
    edges = mesh.edges_sorted
    boundary = edges[trimesh.grouping.group_rows(edges, require_count=1)]
    length = np.linalg.norm(np.diff(mesh.vertices[boundary], axis=1)[:, 0], axis=1)
    high = mesh.vertices[boundary][:, :, 2].min(axis=1) > 6
    rim = truth.outline().length
    assert length[~high].sum() > 0.9 * rim
    assert length[high].sum() < 0.05 * rim, f"open seam length {length[high].sum():.1f} mm"


def test_patches_are_oriented_outwards_with_the_seams(closed_fit):
    _, _, model = closed_fit
    mesh = model.mesh_
    outward = mesh.triangles_center * [1, 1, 0]
    side = mesh.triangles_center[:, 2] < model.cap_height_ - 5
    facing = np.einsum("ij,ij->i", mesh.face_normals[side], outward[side])
    assert np.mean(facing > 0) > 0.99


def test_open_top_has_no_cap_and_one_crossing():
    truth = vase(top=False)
    model = PatchReconstructor(reconstructor=DirectionDelaunay()).fit(sample(truth, 9000))
    assert not model.has_cap_ and len(model.patch_meshes_) == 6
    hits = hits_per_ray(model.mesh_, *side_rays(np.linspace(6, 114, 7), np.arange(0.1, 360, 0.5)))
    assert np.all(hits == 1)
    assert model.mesh_.area == pytest.approx(truth.area, rel=0.03)


def test_missing_side_and_bad_parameters_raise_one_line_errors():
    points = sample(vase(), 6000)
    phi = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360
    gap = points[(phi < 150) | (phi > 270)]
    with pytest.raises(InvalidInputError, match=r"patch sector 3 \(180° to 240°\) has 0 points"):
        PatchReconstructor(reconstructor=DirectionDelaunay()).fit(gap)
    with pytest.raises(InvalidInputError, match="overlap_deg"):
        PatchReconstructor(overlap_deg=70).fit(points)
    with pytest.raises(InvalidInputError, match="shape"):
        PatchReconstructor().fit(points[:, :2])


def test_zip_seam_joins_two_polylines_into_a_strip():
    z = np.linspace(0, 10, 11)
    a = np.c_[np.full(11, 50.0), np.zeros(11), z]  # side a sticks out by 0.5 mm
    b = np.c_[np.full(6, 49.5), np.zeros(6), np.linspace(0, 10, 6)]
    normal = np.array([0.0, 1.0, 0.0])
    faces = zip_seam(a, b, a[:, 2], b[:, 2], normal)
    assert len(faces) == 11 + 6 - 2  # every vertex after the first of each side adds one
    strip = trimesh.Trimesh(np.r_[a, b], faces, process=False)
    assert strip.area == pytest.approx(0.5 * 10, rel=1e-9)  # the 0.5 mm step, 10 mm high
    assert np.all(strip.face_normals @ normal > 0.999)  # facing side b, where there is no material


@pytest.mark.slow
def test_paper_reconstructor_patches_merge_into_one_layer():
    truth = vase()
    model = PatchReconstructor(reconstructor=SurfaceReconstructor(random_state=0))
    model.fit(sample(truth, 7000, noise=0.3))
    angles = np.r_[np.arange(0.1, 360, 1.0), np.arange(0, 360, 60) - 0.1]
    hits = hits_per_ray(model.mesh_, *side_rays(np.linspace(8, model.cap_height_ - 5, 6), angles))
    assert np.all(hits == 1), f"{np.sum(hits != 1)} of {len(hits)} rays cross != 1 time"
    assert model.mesh_.area == pytest.approx(truth.area, rel=0.05)
    probe = trimesh.sample.sample_surface_even(truth, 2000, seed=1)[0]
    _, distance, _ = trimesh.proximity.closest_point(model.mesh_, probe[probe[:, 2] > 5])
    assert np.percentile(distance, 99) < 1.5
