"""The OAK adapter's host-side parts, with depthai installed but no device: URLs, frame and
calibration conversion, error mapping, the grab path over real depthai queues, and depthai's
PointCloud node run on the host against our back-projection. Device tests: `hardware`."""

import datetime
import subprocess
import sys

import numpy as np
import pytest

dai = pytest.importorskip("depthai")

from capture.processing import depth_to_points  # noqa: E402
from drivers.errors import (  # noqa: E402
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceTimeout,
    InvalidDeviceURL,
)
from drivers.oak import OakCamera, parse_url  # noqa: E402
from drivers.oak_messages import (  # noqa: E402
    frame_from_message,
    host_point_cloud,
    img_from_depth,
    intrinsics_from_calibration,
    intrinsics_of,
    vendor_error,
    vendor_errors,
)
from drivers.registry import backend_class, open_camera  # noqa: E402

K = np.array([[441.5, 0.0, 318.25], [0.0, 440.75, 201.5], [0.0, 0.0, 1.0]])
LINK_LOST = (
    "Communication exception - possible device error/misconfiguration. Original message "
    "'Couldn't read data from stream: 'depth' (X_LINK_ERROR)'"
)


def synthetic_depth(seed=0, shape=(400, 640)):
    rng = np.random.default_rng(seed)
    depth = rng.integers(250, 2500, shape).astype(np.uint16)
    depth[rng.random(shape) < 0.3] = 0
    return depth


def test_importing_drivers_never_imports_depthai():
    code = "import sys, drivers, drivers.registry; sys.exit('depthai' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0


def test_the_registry_picks_the_oak_backend():
    assert backend_class("camera", "oak://") is OakCamera


@pytest.mark.parametrize(
    ("url", "device", "options"),
    [
        ("oak://", "", {"width": 640, "height": 400, "fps": 30.0, "align": "auto"}),
        ("oak://1844301011B546F500?fps=15", "1844301011B546F500", {"fps": 15.0}),
        ("oak://192.168.1.44?align=right&pointcloud=1", "192.168.1.44",
         {"align": "right", "pointcloud": 1}),
    ],
)
def test_urls_name_the_device_and_options(url, device, options):
    found, parsed = parse_url(url)
    assert found == device
    assert options.items() <= parsed.items()


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("oak://?fps=fast", "fps='fast' is not a float"),
        ("oak://?exposure=3", "unknown parameter"),
        ("oak://?align=left", "align must be one of"),
        ("oak://?width=0", "must be positive"),
    ],
)
def test_bad_urls_give_one_line_errors(url, message):
    with pytest.raises(InvalidDeviceURL, match=message) as info:
        OakCamera.from_url(url)
    assert "\n" not in str(info.value)


def test_depth_frames_become_frames_in_millimetres():
    depth = synthetic_depth()
    message = img_from_depth(depth, K, timestamp=12.5, sequence=7)
    frame = frame_from_message(message)
    assert frame.depth.dtype == np.uint16 and frame.shape == depth.shape
    np.testing.assert_array_equal(frame.depth, depth)
    assert (frame.timestamp, frame.sequence, frame.color) == (12.5, 7, None)
    frame.depth[:] = 0  # a copy, not a view into depthai's buffer
    assert message.getFrame().any()


def test_a_synced_group_gives_depth_and_colour():
    depth = synthetic_depth(shape=(40, 64))
    rgb = np.random.default_rng(1).integers(0, 255, (40, 64, 3)).astype(np.uint8)
    colour = dai.ImgFrame()
    colour.setFrame(rgb.ravel())
    colour.setType(dai.ImgFrame.Type.RGB888i)
    colour.setWidth(64)
    colour.setHeight(40)
    group = dai.MessageGroup()
    group["depth"] = img_from_depth(depth, K, timestamp=3.0)
    group["color"] = colour
    frame = frame_from_message(group)
    np.testing.assert_array_equal(frame.depth, depth)
    np.testing.assert_array_equal(frame.color, rgb)


def test_non_depth_messages_are_refused_in_one_line():
    colour = dai.ImgFrame()
    colour.setCvFrame(np.zeros((4, 6, 3), np.uint8), dai.ImgFrame.Type.BGR888i)
    with pytest.raises(DeviceError, match="expected a RAW16 depth frame, got BGR888i"):
        frame_from_message(colour)
    group = dai.MessageGroup()
    group["color"] = colour
    with pytest.raises(DeviceError, match="message group without depth"):
        frame_from_message(group)


def test_intrinsics_from_a_saved_calibration(tmp_path):
    handler = dai.CalibrationHandler()
    full = [[880.0, 0.0, 640.0], [0.0, 880.0, 400.0], [0.0, 0.0, 1.0]]
    handler.setCameraIntrinsics(dai.CameraBoardSocket.CAM_C, full, dai.Size2f(1280, 800))
    assert handler.eepromToJsonFile(tmp_path / "calibration.json")
    loaded = dai.CalibrationHandler(tmp_path / "calibration.json")
    k = intrinsics_from_calibration(loaded, dai.CameraBoardSocket.CAM_C, 640, 400)
    np.testing.assert_allclose(k, [[440, 0, 320], [0, 440, 200], [0, 0, 1]])  # halved
    with pytest.raises(DeviceError, match="no intrinsics for CAM_A") as info:
        intrinsics_from_calibration(loaded, dai.CameraBoardSocket.CAM_A, 640, 400)
    assert "\n" not in str(info.value)


def test_frames_carry_their_intrinsics():
    np.testing.assert_allclose(intrinsics_of(img_from_depth(synthetic_depth(), K)), K)
    bare = dai.ImgFrame()
    bare.setCvFrame(np.zeros((4, 6), np.uint16), dai.ImgFrame.Type.RAW16)
    assert intrinsics_of(bare) is None


@pytest.mark.parametrize(
    ("error", "expected", "text"),
    [
        (RuntimeError(LINK_LOST), DeviceDisconnected, "link lost"),
        (dai.XLinkReadError("read failed"), DeviceDisconnected, "link lost"),
        (RuntimeError("No available devices"), DeviceNotFound, "No available devices"),
        (RuntimeError("Cannot find any device with given deviceInfo"), DeviceNotFound, "find"),
        (RuntimeError("Camera CAM_A not found\nmore detail"), DeviceError, "CAM_A not found"),
    ],
)
def test_vendor_errors_map_to_our_tree_with_their_cause(error, expected, text):
    assert type(vendor_error(error, "opening")) is expected
    with pytest.raises(expected, match=text) as info:
        with vendor_errors("oak://: grabbing"):
            raise error
    assert info.value.__cause__ is error and "\n" not in str(info.value)
    assert str(info.value).startswith("oak://: grabbing: ")


class HostFedOak(OakCamera):
    """An OakCamera whose pipeline is replaced by a host queue we feed (no device)."""

    def _open(self):
        self._frames_queue = dai.MessageQueue("depth", 8, False)
        self._intrinsics = K.copy()


def now_plus(seconds):
    return (dai.Clock.now() + datetime.timedelta(seconds=seconds)).total_seconds()


def test_grab_skips_frames_from_before_the_call():
    depth = synthetic_depth(shape=(40, 64))
    with HostFedOak("oak://?timeout=2") as camera:
        camera._frames_queue.send(img_from_depth(depth * 0 + 1, K, now_plus(-1.0), 1))  # stale
        camera._frames_queue.send(img_from_depth(depth, K, now_plus(0.5), 2))
        frame = camera.grab()
    assert frame.sequence == 2
    np.testing.assert_array_equal(frame.depth, depth)


def test_grab_maps_a_closed_queue_and_a_silent_device():
    with HostFedOak("oak://") as camera:
        with pytest.raises(DeviceTimeout, match="no depth frame within 0.05 s"):
            camera.grab(timeout=0.05)
        with pytest.raises(DeviceError, match="pointcloud=1"):
            camera.grab_points()
        camera._frames_queue.close()  # what depthai does when the device goes away
        with pytest.raises(DeviceDisconnected, match="link lost") as info:
            camera.grab()
        assert isinstance(info.value.__cause__, dai.MessageQueue.QueueException)
    with pytest.raises(DeviceError, match="not open"):
        camera.grab()


def test_host_point_cloud_matches_our_back_projection():
    depth = synthetic_depth()
    points = host_point_cloud(depth, K)
    ours = depth_to_points(depth, K)
    assert points.shape == ours.shape == ((depth > 0).sum(), 3)
    np.testing.assert_allclose(points, ours, rtol=1e-5, atol=1e-3)


def _devices():
    return OakCamera.discover()


def test_opening_with_no_device_fails_at_once_in_one_line():
    if _devices():
        pytest.skip("an OAK is connected")
    with pytest.raises(DeviceNotFound, match="no OAK device found") as info:
        open_camera("oak://")
    assert "\n" not in str(info.value)


@pytest.mark.hardware
def test_a_real_device_gives_depth_and_point_clouds():
    if not _devices():
        pytest.skip("no OAK device connected")
    with open_camera("oak://?pointcloud=1") as camera:
        frame = camera.grab()
        points = camera.grab_points()
        assert frame.depth.dtype == np.uint16 and frame.depth.any()
        assert points.ndim == 2 and points.shape[1] == 3 and len(points) > 0
        back = depth_to_points(frame.depth, camera.intrinsics)
        assert abs(np.median(points[:, 2]) - np.median(back[:, 2])) < 0.1 * np.median(back[:, 2])
