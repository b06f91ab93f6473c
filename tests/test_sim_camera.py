"""The simulated depth camera: rendering geometry, coupling to the simulated turntable, the
stereo noise model, objects, URL errors and the unplug knob."""

import importlib.util
import logging

import numpy as np
import pytest
import trimesh

from drivers.errors import DeviceDisconnected, DeviceError, InvalidDeviceURL
from drivers.registry import open_camera, open_turntable
from sim.awkward_objects import AWKWARD, UNTUNED
from sim.camera import SimCamera
from sim.objects import BUILT_IN, ObjectError, load_object
from sim.render import intrinsics_for, make_renderer, render_depth
from sim.station import reset_stations
from sim.stereo_noise import StereoNoise, occluded_in_partner

SMALL = "width=320&height=200"
HAS_EMBREE = importlib.util.find_spec("embreex") is not None


@pytest.fixture(autouse=True)
def _fresh_stations():
    reset_stations()
    yield
    reset_stations()


def exact_sphere_depth(k, shape, centre, radius):
    """Ray-cast depth (H, W) along the optical axis of a sphere, 0 where missed."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]]
    ray = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones(shape)], -1)
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    b = ray @ centre
    disc = b**2 - (centre @ centre - radius**2)
    t = b - np.sqrt(np.maximum(disc, 0))
    return np.where(disc > 0, t * ray[..., 2], 0.0), disc


def test_render_of_a_plane_matches_its_analytic_depth_and_incidence():
    k = intrinsics_for(160, 100, 60.0)
    plane = trimesh.creation.box((2000, 2000, 1)).apply_translation([0, 0, 500.5])  # face z=500
    depth, cos = render_depth(plane.vertices, plane.faces, k, (100, 160))
    np.testing.assert_allclose(depth, 500.0, atol=1e-4)
    v, u = np.mgrid[0:100, 0:160]
    ray = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u, float)], -1)
    np.testing.assert_allclose(cos, 1 / np.linalg.norm(ray, axis=-1), atol=1e-6)


def test_render_of_a_sphere_matches_ray_casting_without_holes():
    k = intrinsics_for(320, 200, 60.0)
    centre, radius = np.array([20.0, -10.0, 600.0]), 150.0
    sphere = trimesh.creation.icosphere(5, radius).apply_translation(centre)
    depth, _ = render_depth(sphere.vertices, sphere.faces, k, (200, 320))
    exact, disc = exact_sphere_depth(k, (200, 320), centre, radius)
    inside = disc > 0.02 * radius**2  # clear of the tessellated silhouette
    assert (depth[inside] > 0).all()  # no cracks between faces
    assert np.abs(depth[inside] - exact[inside]).max() < 0.3  # a level-5 sphere's chord error
    assert (depth[disc < 0] == 0).all()


def test_camera_frames_of_a_ball_match_its_geometry_within_the_noise(tmp_path):
    """End to end: a sphere file on the plate, grabbed with noise, against exact ray casting."""
    radius = 40.0
    trimesh.creation.icosphere(5, radius).export(tmp_path / "ball.stl")
    with open_camera(f"sim://camera?object={tmp_path / 'ball.stl'}&seed=2") as camera:
        depth = camera.grab().depth.astype(float)
        centre = (camera.table_to_camera @ [0, 0, radius, 1])[:3]  # stood on the plate
        exact, disc = exact_sphere_depth(camera.intrinsics, depth.shape, centre, radius)
        fx = camera.intrinsics[0, 0]
        sigma = np.hypot(camera.noise_model.depth_sigma_mm(centre[2], fx), 1 / np.sqrt(12))
    seen = (disc > 0.05 * radius**2) & (depth > 0)
    assert seen.sum() > 3000
    error = depth[seen] - exact[seen]
    assert abs(error.mean()) < 5 * sigma / np.sqrt(seen.sum()) + 0.05  # unbiased
    assert 0.7 * sigma < error.std() < 1.5 * sigma  # the stereo noise, nothing more


def test_large_and_clipped_triangles_render_like_small_ones():
    """A plane of two huge triangles reaching past the image, and the same subdivided."""
    k = intrinsics_for(160, 100, 80.0)
    tilt = trimesh.transformations.rotation_matrix(0.3, [1, 0, 0])  # stays beyond the near plane
    coarse = trimesh.creation.box((3000, 3000, 1)).apply_transform(tilt)
    coarse.apply_translation([0, 0, 800])
    fine = coarse.subdivide().subdivide().subdivide()
    d_coarse, c_coarse = render_depth(coarse.vertices, coarse.faces, k, (100, 160))
    d_fine, c_fine = render_depth(fine.vertices, fine.faces, k, (100, 160))
    assert (d_coarse > 0).all()
    np.testing.assert_allclose(d_coarse, d_fine, rtol=1e-5)
    np.testing.assert_allclose(c_coarse, c_fine, atol=1e-5)


@pytest.mark.skipif(not HAS_EMBREE, reason="embreex not installed")
def test_embree_engine_gives_the_numpy_images():
    k = intrinsics_for(320, 200, 72.0)
    mesh = load_object("bust")
    pose = np.eye(4)
    pose[:3, :3] = trimesh.transformations.rotation_matrix(-1.9, [1, 0, 0])[:3, :3]
    pose[:3, 3] = [0, 40, 380]
    a = make_renderer(mesh.vertices, mesh.faces, engine="numpy").render(pose, k, (200, 320))
    b = make_renderer(mesh.vertices, mesh.faces, engine="embree").render(pose, k, (200, 320))
    assert (a[0] > 0).sum() > 2000
    assert ((a[0] > 0) != (b[0] > 0)).mean() < 1e-3  # pixel centres exactly on silhouettes
    both = (a[0] > 0) & (b[0] > 0)
    np.testing.assert_allclose(a[0][both], b[0][both], atol=1e-3)
    np.testing.assert_allclose(a[1][both], b[1][both], atol=1e-4)


def test_object_turns_with_the_simulated_turntable():
    url = f"sim://camera?object=bust&noise=0&{SMALL}&station=coupled"
    with (
        open_camera(url) as camera,
        open_turntable("sim://turntable?instant=1&station=coupled") as table,
    ):
        at_zero = camera.grab().depth
        table.move_to(90)
        turned = camera.grab().depth
        expected, _ = camera.render(90)
    assert (np.abs(turned.astype(float) - at_zero) > 10).sum() > 200  # the view changed
    np.testing.assert_array_equal(turned, np.round(expected).astype(np.uint16))


@pytest.mark.parametrize("sign", [1, -1])
def test_every_view_maps_back_onto_the_true_object(sign):
    """Points seen at table angle θ, taken to the table frame and turned by −sign·θ, lie on
    `true_object_mesh()`: the pose, the angle coupling and the rotation sense agree."""
    camera = SimCamera(f"sim://camera?object=bust&noise=0&{SMALL}&rotation_sign={sign}")
    truth = camera.true_object_mesh()
    k = camera.intrinsics
    for angle in (0.0, 70.0, 200.0):
        depth, _ = camera.render(angle)
        v, u = np.nonzero(depth)
        z = depth[v, u].astype(float)
        points = np.column_stack([(u - k[0, 2]) / k[0, 0] * z, (v - k[1, 2]) / k[1, 1] * z, z])
        table = points @ camera.camera_to_table[:3, :3].T + camera.camera_to_table[:3, 3]
        on_object = (table[:, 2] > 1.0) & (np.hypot(table[:, 0], table[:, 1]) < 60)
        a = np.radians(-sign * angle)
        back = table[on_object] @ np.array(
            [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
        ).T
        _, distance, _ = trimesh.proximity.closest_point(truth, back[::7])
        assert len(back) > 1500 and np.percentile(distance, 99) < 0.05


def test_noise_is_deterministic_with_a_seed():
    url = f"sim://camera?seed=3&{SMALL}&object=box"
    with open_camera(url) as a, open_camera(url) as b:
        first = a.grab().depth
        np.testing.assert_array_equal(first, b.grab().depth)
        assert not np.array_equal(a.grab().depth, first)  # the next frame has its own noise
    with open_camera(url.replace("seed=3", "seed=4")) as c:
        assert not np.array_equal(c.grab().depth, first)


def test_depth_noise_grows_with_the_square_of_depth():
    model, fx = StereoNoise(edge_dropout=0.0), 440.0
    fb = fx * model.baseline_mm
    # 1/8 px quantisation adds (1/8)²/12 to the disparity variance, on average over depths
    sigma_px = np.hypot(model.sigma_px, 1 / model.subpixel_levels / np.sqrt(12))
    rng = np.random.default_rng(0)
    spread = {}
    for z0 in (800.0, 1600.0):
        z = np.tile(z0 * np.linspace(0.97, 1.03, 400), (100, 1))  # many disparity phases
        noisy = model.apply(z, np.ones_like(z), fx, rng).astype(float)
        assert (noisy > 0).all()
        error = (noisy - z) * (z0 / z) ** 2  # scaled to depth z0
        assert abs(error.mean()) < 0.1 * error.std()  # unbiased
        spread[z0] = error.std()
        assert spread[z0] == pytest.approx(sigma_px * z0**2 / fb, rel=0.1)
    assert spread[1600.0] / spread[800.0] == pytest.approx(4.0, rel=0.1)


def test_grazing_pixels_and_stereo_shadows_go_missing():
    model, fx = StereoNoise(edge_dropout=0.0), 440.0
    depth = np.full((60, 200), 800.0)
    depth[20:40, 100:140] = 400.0  # a box in front of a wall
    cosine = np.ones_like(depth)
    cosine[:, :10] = 0.1  # a grazing strip
    noisy = model.apply(depth, cosine, fx, np.random.default_rng(0))
    assert (noisy[:, :10] == 0).all()
    shadow = fx * model.baseline_mm * (1 / 400 - 1 / 800)  # disparity jump, px (≈ 41)
    hidden = occluded_in_partner(fx * model.baseline_mm / depth)
    for row in range(20, 40):
        columns = np.flatnonzero(hidden[row])
        assert columns.max() == 99  # just left of the box, as wide as the disparity jump
        assert abs(len(columns) - (shadow - model.occlusion_tol_px)) <= 1
        assert (noisy[row, columns] == 0).all()
    assert not hidden[:20].any() and (noisy[:20, 10:] > 0).all()  # nothing hidden above it


def test_silhouette_edges_of_the_object_lose_pixels():
    camera = SimCamera(f"sim://camera?{SMALL}&object=vase")
    camera.open()
    depth, cos = camera.render(0)
    noisy = camera.noise_model.apply(depth, cos, camera.intrinsics[0, 0], np.random.default_rng(0))
    assert (noisy[cos < camera.noise_model.min_cos] == 0).all()
    lost = (noisy == 0) & (depth > 0)
    assert 0.01 * (depth > 0).sum() < lost.sum() < 0.3 * (depth > 0).sum()


def test_intrinsics_and_frame_shape_follow_the_url():
    with open_camera(f"sim://camera?{SMALL}&hfov=72") as camera:
        frame = camera.grab()
        assert frame.depth.shape == (200, 320) and frame.depth.dtype == np.uint16
        assert camera.intrinsics[0, 0] == pytest.approx(160 / np.tan(np.radians(36)))


def test_realtime_paces_grabs_at_the_frame_rate(monkeypatch):
    waits = []
    monkeypatch.setattr("sim.camera.time.sleep", waits.append)
    with open_camera(f"sim://camera?{SMALL}&realtime=1&fps=5&noise=0") as camera:
        for _ in range(3):
            camera.grab()
    assert len(waits) == 2 and all(0 < w <= 0.2 for w in waits)


def test_disconnect_knob_unplugs_once_and_reopen_reconnects():
    camera = open_camera(f"sim://camera?{SMALL}&disconnect_after=2")
    camera.grab()
    camera.grab()
    with pytest.raises(DeviceDisconnected, match="disconnected"):
        camera.grab()
    with pytest.raises(DeviceDisconnected):
        camera.grab()
    camera.reconnect()
    assert camera.grab().depth.any()
    camera.close()
    camera.close()
    with pytest.raises(DeviceError, match="not open"):
        camera.grab()


@pytest.mark.parametrize("name", sorted(set(BUILT_IN) - set(AWKWARD) - set(UNTUNED)))
def test_built_in_objects_stand_on_the_plate(name):
    mesh = load_object(name)
    assert 20_000 <= len(mesh.faces) <= 60_000
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert mesh.bounds[0, 2] == pytest.approx(0.0)
    np.testing.assert_allclose(mesh.bounds[:, :2].sum(0), 0, atol=1e-9)
    assert 80 <= mesh.extents[2] <= 130 and mesh.extents[:2].max() < 200  # fits the plate


def test_mesh_files_stand_on_the_plate(tmp_path, caplog):
    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(3, 30.0).apply_translation([500, 7, -40]).export(path)
    mesh = load_object(path)
    assert mesh.bounds[0, 2] == pytest.approx(0.0)
    assert np.abs(mesh.bounds.mean(0)[:2]).max() < 1e-9
    inside_out = trimesh.creation.icosphere(3, 30.0)
    inside_out.invert()
    inside_out.export(tmp_path / "inside_out.stl")
    assert load_object(tmp_path / "inside_out.stl").volume > 0  # turned outward for culling
    trimesh.creation.icosphere(2, 0.03).export(tmp_path / "metres.stl")
    with caplog.at_level(logging.WARNING, logger="sim.objects"):
        load_object(tmp_path / "metres.stl")
    assert "metres" in caplog.text


def write_point_cloud(path):
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(50, 3))).export(path)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (None, "no such file"),
        (lambda p: p.mkdir(), "not a file"),
        (lambda p: p.write_text("ply\nformat nonsense\n"), "unreadable mesh"),
        (write_point_cloud, "holds no triangles"),
    ],
    ids=["missing", "directory", "unreadable", "points-only"],
)
def test_bad_object_files_give_one_line_errors(tmp_path, make, message):
    path = tmp_path / "thing.ply"
    if make:
        make(path)
    with pytest.raises(ObjectError, match=message) as info:
        open_camera(f"sim://camera?object={path}")
    assert "\n" not in str(info.value) and str(path.name) in str(info.value)


@pytest.mark.parametrize(
    ("query", "message"),
    [
        ("width=wide", "width='wide' is not a int"),
        ("zoom=2", "unknown parameter"),
        ("engine=opengl", "engine must be one of"),
        ("rotation_sign=2", "rotation_sign must be 1 or -1"),
        ("noise=-1", "noise must be >= 0"),
    ],
)
def test_bad_urls_give_one_line_errors(query, message):
    with pytest.raises(InvalidDeviceURL, match=message) as info:
        open_camera(f"sim://camera?{query}")
    assert "\n" not in str(info.value)


def test_calibration_finds_the_reversed_sense_of_rotation(tmp_path):
    """With rotation_sign=-1 the views turn clockwise, and calibration must see that."""
    from capture.axis_calibration import DumbbellTarget, calibrate
    from capture.calibration import Calibration

    target = DumbbellTarget()
    target.mesh().export(tmp_path / "dumbbell.stl")
    url = f"sim://camera?object={tmp_path / 'dumbbell.stl'}&rotation_sign=-1&station=ccw"
    with (
        open_camera(url) as camera,
        open_turntable("sim://turntable?instant=1&station=ccw") as table,
    ):
        estimated = calibrate(camera, table, angles=range(0, 360, 45), target=target)
        truth = Calibration.from_sim(camera)
    assert estimated.rotation_sign == -1 == truth.rotation_sign
    assert np.linalg.norm(estimated.axis_origin - truth.axis_origin) < 1.0


@pytest.fixture
def grbl_board(tmp_path):
    """A GRBL board on a pseudo-terminal, outside any simulated station (as real hardware is)."""
    from sim.grbl_firmware import GrblFirmware
    from sim.serial_ports import PtyTransport

    with PtyTransport(GrblFirmware(), link=str(tmp_path / "ttyGRBL")) as transport:
        yield f"grbl://{transport.port_name}"


def test_the_camera_follows_the_angle_any_turntable_reports(grbl_board):
    from capture.station import follow_turntable

    with (
        open_camera("sim://camera?object=vase&noise=0&width=96&height=64&station=hil") as camera,
        open_turntable(grbl_board) as table,
    ):
        still = camera.grab().depth
        follow_turntable(camera, table)
        table.move_to(90)
        turned = camera.grab().depth
        assert np.array_equal(turned, np.round(camera.render(90)[0]).astype(np.uint16))
        assert not np.array_equal(turned, still)
        camera.follow(None)  # back to the station's own (absent) turntable: angle 0
        assert np.array_equal(camera.grab().depth, still)


def test_calibrate_runs_end_to_end_against_a_grbl_board(grbl_board, tmp_path, capsys):
    """Hardware in the loop: `scanstation calibrate --turntable grbl://…` with the simulated
    camera used to fail with 'cannot tell the direction of rotation' (every view the same)."""
    from capture.cli import main

    out = tmp_path / "calibration.json"
    assert main(["calibrate", "--turntable", grbl_board, "--views", "6", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "rotation sign +1" in printed and out.exists()
    distance, angle = (float(v) for v in
                       printed.split("true axis: ")[1].replace("mm,", "").split("°")[0].split())
    assert distance < 1.0 and angle < 1.0


def test_a_station_with_a_grbl_table_and_the_simulated_camera_follows_it(grbl_board):
    """`scanstation scan --turntable grbl://…` without a camera URL: hardware in the loop."""
    from capture.station import open_station

    with open_station(camera_url="sim://camera?noise=0&width=96&height=64",
                      turntable_url=grbl_board) as station:
        station.turntable.move_to(120)
        depth = station.camera.grab().depth
        assert station.camera.table_angle() == 120
        assert np.array_equal(depth, np.round(station.camera.render(120)[0]).astype(np.uint16))
