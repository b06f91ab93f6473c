"""Calibration: the data class and its file, the geometric fits, the axis from a target."""

import numpy as np
import pytest

from capture.axis_calibration import (
    DumbbellTarget,
    calibrate,
    calibrate_from_views,
    estimate_axis,
    find_spheres,
    fit_circle_3d,
)
from capture.calibration import Calibration, CalibrationError

K = np.array([[440.0, 0.0, 320.0], [0.0, 440.0, 200.0], [0.0, 0.0, 1.0]])
SHAPE = (400, 640)


def look_at_table(distance=450.0, height=250.0, target_z=80.0, tilt_deg=0.0):
    """(4, 4) table → camera; ``tilt_deg`` leans the table about its x axis (a misaligned axis)."""
    centre = np.array([0.0, -distance, height])
    forward = np.array([0.0, 0.0, target_z]) - centre
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    camera_to_table = np.eye(4)
    camera_to_table[:3, :3] = np.column_stack([right, np.cross(forward, right), forward])
    camera_to_table[:3, 3] = centre
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    lean = np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])
    return np.linalg.inv(lean @ camera_to_table)


def render_target(table_to_camera, target, angle_deg, sign=1, noise_mm=0.0, rng=None):
    """uint16 depth (H, W) mm of the target's spheres and a 200 mm plate, ray-cast exactly."""
    v, u = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    a = np.radians(sign * angle_deg)
    depth = np.full(SHAPE, np.inf)
    for x in (-target.half_span_mm, target.half_span_mm):
        centre = np.array([x * np.cos(a), x * np.sin(a), target.centre_height_mm])
        cc = table_to_camera[:3, :3] @ centre + table_to_camera[:3, 3]
        aa, b = (rays**2).sum(-1), rays @ cc
        disc = b**2 - aa * (cc @ cc - target.sphere_radius_mm**2)
        t = (b - np.sqrt(np.maximum(disc, 0))) / aa
        depth = np.where((disc >= 0) & (t > 0) & (t < depth), t, depth)
    normal, origin = table_to_camera[:3, 2], table_to_camera[:3, 3]
    t = (normal @ origin) / (rays @ normal)
    hit = rays * t[..., None] - origin
    radial = np.linalg.norm(hit - (hit @ normal)[..., None] * normal, axis=-1)
    depth = np.where((t > 0) & (radial <= 200) & (t < depth), t, depth)
    if noise_mm:
        depth = depth + np.random.default_rng(rng).normal(0, noise_mm, SHAPE)
    return np.where(np.isfinite(depth), np.round(depth), 0).astype(np.uint16)


def axis_errors(estimated: Calibration, truth: Calibration) -> tuple[float, float]:
    """(distance mm of the estimated axis origin from the true one, angle ° between the axes)."""
    distance = np.linalg.norm(estimated.axis_origin - truth.axis_origin)
    cosine = np.clip(estimated.axis_direction @ truth.axis_direction, -1, 1)
    return float(distance), float(np.degrees(np.arccos(cosine)))


def test_json_round_trip_and_save_load(tmp_path):
    calibration = Calibration(K, np.linalg.inv(look_at_table(tilt_deg=3)), -1, 0.25)
    again = Calibration.from_json(calibration.to_json())
    np.testing.assert_array_equal(again.intrinsics, K)
    np.testing.assert_array_equal(again.camera_to_table, calibration.camera_to_table)
    assert (again.rotation_sign, again.residual_mm) == (-1, 0.25)
    calibration.save(tmp_path / "station.json")
    loaded = Calibration.load(tmp_path / "station.json")
    np.testing.assert_array_equal(loaded.camera_to_table, calibration.camera_to_table)
    np.testing.assert_allclose(
        (loaded.table_transform(30) @ calibration.table_to_camera[:, 3])[:3], 0, atol=1e-9
    )


@pytest.mark.parametrize(
    "text, message",
    [
        ("{", "not valid JSON"),
        ('{"format": "other"}', "not a calibration file"),
        ('{"format": "scanstation-calibration/1", "intrinsics": []}', "lacks camera_to_table"),
    ],
)
def test_bad_files_give_one_line_errors(text, message, tmp_path):
    with pytest.raises(CalibrationError, match=message) as info:
        Calibration.from_json(text)
    assert "\n" not in str(info.value)
    with pytest.raises(CalibrationError, match="cannot read calibration"):
        Calibration.load(tmp_path / "missing.json")


def test_invalid_matrices_are_refused():
    sheared = np.eye(4)
    sheared[0, 1] = 0.3
    with pytest.raises(CalibrationError, match="not a rigid transform"):
        Calibration(K, sheared)
    with pytest.raises(CalibrationError, match="intrinsics"):
        Calibration(np.eye(3) * -1, np.eye(4))
    with pytest.raises(CalibrationError, match="rotation_sign"):
        Calibration(K, np.eye(4), rotation_sign=2)


def test_from_axis_puts_the_axis_where_asked():
    origin, direction = np.array([5.0, 80.0, 450.0]), np.array([0.1, -1.0, -0.3])
    calibration = Calibration.from_axis(K, origin, direction)
    np.testing.assert_allclose(calibration.axis_origin, origin)
    np.testing.assert_allclose(calibration.axis_direction, direction / np.linalg.norm(direction))
    # Points on the axis stay on the axis at every angle; the frame's y looks away from the camera.
    on_axis = np.r_[origin + 40 * direction, 1.0]
    for angle in (0, 45, 200):
        np.testing.assert_allclose(calibration.table_transform(angle)[:2] @ on_axis, 0, atol=1e-9)
    assert calibration.table_to_camera[2, 1] > 0


def test_circle_fit_recovers_a_known_circle():
    rng = np.random.default_rng(0)
    centre, normal, radius = np.array([10.0, -40.0, 500.0]), np.array([0.2, -0.9, -0.3]), 70.0
    normal /= np.linalg.norm(normal)
    e1 = np.cross(normal, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    t = rng.uniform(0, 2 * np.pi, 40)
    points = centre + radius * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2))
    points += rng.normal(0, 0.1, points.shape)
    c, n, r, residuals = fit_circle_3d(points)
    np.testing.assert_allclose(c, centre, atol=0.1)
    assert abs(abs(n @ normal) - 1) < 1e-5 and abs(r - radius) < 0.1
    assert residuals.shape == (40,) and np.sqrt(np.mean(residuals**2)) < 0.25


@pytest.mark.parametrize("sign", [1, -1])
def test_estimate_axis_finds_axis_and_direction_of_rotation(sign):
    truth = Calibration(K, np.linalg.inv(look_at_table(tilt_deg=4)), sign)
    angles = np.arange(0, 360, 30.0)
    a = np.radians(sign * angles)
    arms = np.concatenate([np.c_[s * 70 * np.cos(a), s * 70 * np.sin(a)] for s in (1, -1)])
    centres_table = np.c_[arms, np.full(len(arms), 90.0), np.ones(len(arms))]
    centres = (centres_table @ truth.table_to_camera.T)[:, :3]
    centre, direction, found_sign, residuals = estimate_axis(centres, np.r_[angles, angles])
    assert found_sign == sign
    np.testing.assert_allclose(direction, truth.axis_direction, atol=1e-9)
    np.testing.assert_allclose(centre, truth.axis_origin + 90 * truth.axis_direction, atol=1e-6)
    assert residuals.max() < 1e-6
    with pytest.raises(CalibrationError, match="direction of rotation"):
        estimate_axis(centres[[0, 3, 6, 9]], [0, 90, 180, 270])


def test_find_spheres_in_a_cloud_with_a_plane():
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(4000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    facing = directions[directions[:, 2] < 0][:1500]  # the caps seen from the camera at 0
    truth = np.array([[-60.0, 0, 500], [70.0, 10, 520]])
    spheres = [c + 20 * facing + rng.normal(0, 0.3, facing.shape) for c in truth]
    plane = np.c_[rng.uniform(-150, 150, (5000, 2)), np.full(5000, 560.0)]
    found = find_spheres(np.concatenate(spheres + [plane]), 20.0, rng=0)
    assert len(found) == 2
    found = np.array(sorted(found, key=lambda c: c[0]))
    np.testing.assert_allclose(found, truth, atol=0.2)


@pytest.mark.parametrize("sign", [1, -1])
def test_calibrate_from_rendered_views_within_tolerance(sign):
    table_to_camera = look_at_table(tilt_deg=5)
    truth = Calibration(K, np.linalg.inv(table_to_camera), sign)
    target = DumbbellTarget()
    angles = np.arange(0, 360, 30.0)
    depths = [render_target(table_to_camera, target, a, sign, 1.0, i) for i, a in enumerate(angles)]
    estimated = calibrate_from_views(depths, angles, K, target)
    distance, angle = axis_errors(estimated, truth)
    assert distance < 1.0 and angle < 0.5
    assert estimated.rotation_sign == sign and estimated.residual_mm < 1.0


def test_too_few_target_detections_names_what_is_missing():
    table_to_camera = look_at_table()
    target = DumbbellTarget()
    depths = [render_target(table_to_camera, target, a) for a in (0, 30, 60)]
    depths += [np.zeros(SHAPE, np.uint16)] * 3
    with pytest.raises(CalibrationError, match=r"found at only 3 of 6 angles \(need 4\)") as info:
        calibrate_from_views(depths, [0, 30, 60, 90, 120, 150], K, target)
    assert "\n" not in str(info.value)


def test_calibrate_the_simulated_station_within_tolerance(tmp_path):
    """Against the sim's true pose, with its depth noise on (station 'calibration')."""
    from drivers.registry import open_camera, open_turntable

    path = tmp_path / "dumbbell.stl"
    DumbbellTarget().mesh().export(path)
    camera_url = f"sim://camera?object={path}&seed=0&station=calibration"
    with (
        open_camera(camera_url) as camera,
        open_turntable("sim://turntable?instant=1&station=calibration") as table,
    ):
        estimated = calibrate(camera, table)
        truth = Calibration.from_sim(camera)
    distance, angle = axis_errors(estimated, truth)
    assert distance < 1.0 and angle < 0.5, f"axis off by {distance:.2f} mm, {angle:.2f}°"
    assert estimated.rotation_sign == truth.rotation_sign
