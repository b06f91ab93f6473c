"""Depth → object-frame points: back-projection, table frame, crop, voxel grid, outliers."""

import numpy as np
import pytest

from capture.axis_calibration import fit_sphere_centre
from capture.calibration import Calibration
from capture.processing import ViewProcessor, depth_to_points, project_points, voxel_downsample
from capture.volume import Cylinder
from reconstruct.errors import InvalidInputError

K = np.array([[440.0, 0.0, 320.0], [0.0, 440.0, 200.0], [0.0, 0.0, 1.0]])
SHAPE = (400, 640)


def look_at_table(distance=450.0, height=250.0, target_z=80.0) -> np.ndarray:
    """(4, 4) table → camera for a camera on the table's -y side looking at the axis."""
    centre = np.array([0.0, -distance, height])
    forward = np.array([0.0, 0.0, target_z]) - centre
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    camera_to_table = np.eye(4)
    camera_to_table[:3, :3] = np.column_stack([right, np.cross(forward, right), forward])
    camera_to_table[:3, 3] = centre
    return np.linalg.inv(camera_to_table)


def render(table_to_camera, spheres=(), plate_radius=None, wall_mm=None, angle_deg=0.0):
    """Exact float depth (H, W) mm of spheres [(centre in object frame, radius)], the plate disc
    z = 0 and a fronto-parallel wall, seen with the table at ``angle_deg`` (0 = no hit)."""
    v, u = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    turn = np.eye(4)
    turn[:2, :2] = [[c, -s], [s, c]]
    pose = table_to_camera @ turn
    depth = np.full(SHAPE, np.inf)
    for centre, radius in spheres:
        cc = pose[:3, :3] @ centre + pose[:3, 3]
        a, b = (rays**2).sum(-1), rays @ cc
        disc = b**2 - a * (cc @ cc - radius**2)
        t = (b - np.sqrt(np.maximum(disc, 0))) / a
        depth = np.where((disc >= 0) & (t > 0) & (t < depth), t, depth)
    if plate_radius is not None:
        normal, origin = table_to_camera[:3, 2], table_to_camera[:3, 3]
        t = (normal @ origin) / (rays @ normal)
        hit = rays * t[..., None] - origin
        radial = np.linalg.norm(hit - (hit @ normal)[..., None] * normal, axis=-1)
        depth = np.where((t > 0) & (radial <= plate_radius) & (t < depth), t, depth)
    if wall_mm is not None:
        depth = np.minimum(depth, wall_mm)
    return np.where(np.isfinite(depth), depth, 0.0)


def test_flat_depth_back_projects_to_plane_with_principal_point_on_axis():
    depth = np.full(SHAPE, 500, dtype=np.uint16)
    points = depth_to_points(depth, K)
    assert points.shape == (SHAPE[0] * SHAPE[1], 3)
    np.testing.assert_array_equal(points[:, 2], 500.0)
    centre = points[200 * SHAPE[1] + 320]
    np.testing.assert_allclose(centre, [0.0, 0.0, 500.0], atol=1e-4)
    corner = points[0]  # pixel (u, v) = (0, 0)
    np.testing.assert_allclose(corner, [-320 / 440 * 500, -200 / 440 * 500, 500], rtol=1e-6)


def test_zero_depth_pixels_are_dropped_and_projection_inverts_back_projection():
    rng = np.random.default_rng(0)
    depth = rng.integers(300, 900, SHAPE).astype(np.uint16)
    depth[rng.random(SHAPE) < 0.3] = 0
    points = depth_to_points(depth, K)
    assert len(points) == np.count_nonzero(depth)
    uv, z = project_points(points, K)
    v, u = np.nonzero(depth)
    np.testing.assert_allclose(uv, np.column_stack([u, v]), atol=1e-3)
    np.testing.assert_allclose(z, depth[v, u], rtol=1e-6)


def test_bad_inputs_raise_one_line_errors():
    with pytest.raises(InvalidInputError, match="depth must be an"):
        depth_to_points(np.zeros((4, 4, 2)), K)
    with pytest.raises(InvalidInputError, match="intrinsics"):
        depth_to_points(np.zeros((4, 4)), np.eye(2))
    calibration = Calibration.from_axis(K, [0, 0, 500], [0, -1, 0])
    with pytest.raises(InvalidInputError, match="empty working volume"):
        ViewProcessor(calibration, Cylinder(100, 50, 10)).process(np.zeros(SHAPE), 0)


def test_table_frame_round_trip_with_known_calibration():
    table_to_camera = look_at_table()
    calibration = Calibration(K, np.linalg.inv(table_to_camera), rotation_sign=-1)
    depth = render(table_to_camera, spheres=[([0, 0, 80], 60)])
    processor = ViewProcessor(calibration, Cylinder(1e4, -1e4, 1e4), voxel_mm=None)
    processor.outlier_neighbors = 0
    angle = 37.0
    points = processor.process(depth, angle)
    assert len(points) == np.count_nonzero(depth)
    back = np.c_[points, np.ones(len(points))] @ np.linalg.inv(calibration.table_transform(angle)).T
    uv, z = project_points(back[:, :3], K)
    v, u = np.nonzero(depth)
    np.testing.assert_allclose(uv, np.column_stack([u, v]), atol=1e-2)
    np.testing.assert_allclose(z, depth[v, u], rtol=1e-5)


@pytest.mark.parametrize("sign", [1, -1])
def test_every_view_lands_in_the_one_object_frame(sign):
    table_to_camera = look_at_table()
    calibration = Calibration(K, np.linalg.inv(table_to_camera), rotation_sign=sign)
    ball = np.array([40.0, 10.0, 50.0])
    processor = ViewProcessor(calibration, Cylinder(150, 3, 200), voxel_mm=1.0)
    for angle in (0.0, 70.0, 165.0, 290.0):
        depth = render(table_to_camera, [(ball, 25.0)], angle_deg=sign * angle)
        points = processor.process(depth, angle)
        centre = fit_sphere_centre(points, 25.0, points.mean(axis=0))
        np.testing.assert_allclose(centre, ball, atol=0.2)


def test_crop_removes_plate_and_background():
    table_to_camera = look_at_table()
    calibration = Calibration(K, np.linalg.inv(table_to_camera))
    ball, radius = np.array([0.0, 0.0, 60.0]), 40.0
    depth = render(table_to_camera, [(ball, radius)], plate_radius=200, wall_mm=900)
    depth = np.round(depth).astype(np.uint16)
    everything = ViewProcessor(calibration, Cylinder(1e4, -1e4, 1e4), None, 0).process(depth, 0)
    plate = np.abs(everything[:, 2]) < 1.0
    assert plate.sum() > 10_000 and (everything[:, 1] > 300).sum() > 10_000  # plate and wall
    points = ViewProcessor(calibration, Cylinder(150, 3, 300), None, 0).process(depth, 0)
    assert points[:, 2].min() >= 3 and np.hypot(points[:, 0], points[:, 1]).max() <= 150
    # Only the ball is left: every point on its surface (uint16 rounding: <= 0.5 mm along a ray).
    np.testing.assert_allclose(np.linalg.norm(points - ball, axis=1), radius, atol=0.6)
    assert len(points) > 3000


def test_limits_name_the_image_edge_the_side_and_the_top_the_object_reaches():
    table_to_camera = look_at_table()
    calibration = Calibration(K, np.linalg.inv(table_to_camera))

    def limits(centre, radius, top=300.0):
        processor = ViewProcessor(calibration, Cylinder(150, 3, top), 2.0, 0)
        depth = np.round(render(table_to_camera, [(np.array(centre, float), radius)],
                                plate_radius=200, wall_mm=900)).astype(np.uint16)
        return processor.limits(depth, 0.0, processor.process(depth, 0.0))
    assert limits((0, 0, 60), 40) == ()  # a ball well inside (the plate is cut, not reached)
    assert limits((0, 0, 100), 40, top=120) == ("roof",)
    assert limits((120, 0, 60), 40) == ("wall",)
    # a ball filling the view: the image's edge sees into the volume (and the ball its side)
    assert limits((0, 0, 60), 260) == ("image edge", "wall")
    assert limits((0, 0, 60), 400) == ()  # all of it beyond the volume


def test_voxel_downsample_one_mean_per_occupied_voxel():
    rng = np.random.default_rng(1)
    points = rng.uniform(-10, 10, (2000, 3))
    voxel = 2.5
    out = voxel_downsample(points, voxel)
    cells = np.floor(points / voxel).astype(int)
    groups: dict = {}
    for cell, p in zip(map(tuple, cells), points, strict=True):
        groups.setdefault(cell, []).append(p)
    expected = np.array([np.mean(groups[c], axis=0) for c in sorted(groups)])
    assert out.shape == (len(groups), 3)
    np.testing.assert_allclose(out, expected, atol=1e-12)
    # Every output point lies in a distinct voxel, the one its inputs came from.
    assert len({tuple(c) for c in np.floor(out / voxel).astype(int)}) == len(groups)


def test_voxel_downsample_edge_cases():
    assert voxel_downsample(np.empty((0, 3)), 1.0).shape == (0, 3)
    same = np.tile([[1.2, 3.4, 5.6]], (7, 1))
    np.testing.assert_allclose(voxel_downsample(same, 1.0), same[:1])
    with pytest.raises(InvalidInputError, match="voxel_mm"):
        voxel_downsample(same, 0.0)


def test_statistical_outliers_are_removed():
    table_to_camera = look_at_table()
    calibration = Calibration(K, np.linalg.inv(table_to_camera))
    ball, radius = np.array([0.0, 0.0, 60.0]), 40.0
    depth = np.round(render(table_to_camera, [(ball, radius)])).astype(np.uint16)
    v, u = np.nonzero(depth)
    rng = np.random.default_rng(2)
    pick = rng.choice(len(v), 30, replace=False)
    depth[v[pick], u[pick]] -= 60  # flying pixels 60 mm in front of the surface
    volume = Cylinder(150, 3, 300)
    kept = ViewProcessor(calibration, volume, voxel_mm=2.0).process(depth, 0)
    raw = ViewProcessor(calibration, volume, voxel_mm=2.0, outlier_neighbors=0).process(depth, 0)
    off = np.abs(np.linalg.norm(raw - ball, axis=1) - radius) > 5
    assert off.sum() >= 25
    np.testing.assert_allclose(np.linalg.norm(kept - ball, axis=1), radius, atol=1.0)
    assert len(kept) >= len(raw) - off.sum() - 0.02 * len(raw)
