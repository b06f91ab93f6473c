"""What every `DepthCamera` backend must do (like scikit-learn's check_estimator).

Runs on the simulated camera always (both render engines when embreex is installed); on a real
camera, marked ``hardware``, when SCANSTATION_CAMERA_URL is set (e.g. ``oak://``) or else when
depthai is installed and sees an OAK.
"""

import importlib.util
import os
import threading
import urllib.parse

import numpy as np
import pytest

import drivers
from drivers import DepthCamera, DeviceError
from drivers.registry import backend_class
from sim.station import reset_stations


def _hardware_url() -> str | None:
    """SCANSTATION_CAMERA_URL, else the first OAK that depthai sees (None without one)."""
    if os.environ.get("SCANSTATION_CAMERA_URL"):
        return os.environ["SCANSTATION_CAMERA_URL"]
    if importlib.util.find_spec("depthai") is None:
        return None
    from drivers.oak import OakCamera

    try:
        found = OakCamera.discover()
    except DeviceError:
        return None
    return found[0] if found else None


_HARDWARE_URL = _hardware_url()
_NO_EMBREE = importlib.util.find_spec("embreex") is None
BACKENDS = [
    pytest.param("sim://camera?station=conformance&width=320&height=200", id="sim"),
    pytest.param(
        "sim://camera?station=conformance&width=320&height=200&engine=embree&object=bust",
        id="sim-embree",
        marks=[pytest.mark.skipif(_NO_EMBREE, reason="embreex not installed")],
    ),
    pytest.param(
        _HARDWARE_URL,
        id="hardware",
        marks=[pytest.mark.hardware]
        + ([] if _HARDWARE_URL else [pytest.mark.skip(
            reason="no camera: no OAK seen and SCANSTATION_CAMERA_URL unset")]),
    ),
]


@pytest.fixture(params=BACKENDS)
def url(request):
    reset_stations()
    yield request.param
    reset_stations()


@pytest.fixture
def camera(url):
    with drivers.open_camera(url) as device:
        yield device


def test_open_gives_an_open_camera(camera):
    assert isinstance(camera, DepthCamera) and camera.is_open
    assert "open" in repr(camera) and camera.url


def test_open_close_twice_and_close_is_safe_to_repeat(url):
    device = drivers.open_camera(url)
    device.close()
    device.close()
    assert not device.is_open
    device.open()
    assert device.is_open and device.grab().depth.size
    device.close()
    device.close()
    assert not device.is_open


def test_context_manager_closes(url):
    with drivers.open_camera(url) as device:
        assert device.is_open
    assert not device.is_open


def test_intrinsics_are_a_pinhole_matrix(camera):
    k = camera.intrinsics
    assert k.shape == (3, 3) and k.dtype == np.float64
    np.testing.assert_array_equal(k[2], [0, 0, 1])
    assert k[0, 0] > 0 and k[1, 1] > 0 and k[0, 1] == 0 and k[1, 0] == 0
    height, width = camera.grab().depth.shape
    assert 0 < k[0, 2] < width and 0 < k[1, 2] < height
    k[0, 0] = -1  # a copy: the camera's own matrix is untouched
    assert camera.intrinsics[0, 0] > 0


def test_frames_are_uint16_millimetres_with_increasing_stamps(camera):
    frames = [camera.grab() for _ in range(4)]
    for frame in frames:
        assert frame.depth.dtype == np.uint16 and frame.depth.ndim == 2
        assert frame.depth.shape == frames[0].depth.shape == frame.shape
        assert frame.depth.flags.c_contiguous and frame.depth.any()
        assert frame.color is None or frame.color.shape == (*frame.shape, 3)
    stamps = [f.timestamp for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    sequence = [f.sequence for f in frames]
    assert all(b > a for a, b in zip(sequence, sequence[1:], strict=False))
    valid = frames[0].depth[frames[0].depth > 0]
    assert 100 < np.median(valid) < 10_000  # millimetres, not metres or micrometres


def test_frames_are_not_shared_between_grabs(camera):
    first = camera.grab()
    kept = first.depth.copy()
    camera.grab()
    np.testing.assert_array_equal(first.depth, kept)


def test_grab_on_a_closed_camera_raises_a_device_error(url):
    device = drivers.open_camera(url)
    device.close()
    with pytest.raises(DeviceError) as info:
        device.grab()
    assert "\n" not in str(info.value)


def test_grabs_from_two_threads_each_get_whole_frames(camera):
    results, errors = [], []

    def worker():
        try:
            results.extend(camera.grab() for _ in range(3))
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors and len(results) == 6
    assert len({f.sequence for f in results}) == 6


def test_discover_lists_urls_of_the_backend(url):
    cls = backend_class("camera", url)
    scheme = urllib.parse.urlsplit(url).scheme
    found = cls.discover()
    assert isinstance(found, list)
    assert all(isinstance(u, str) and u.startswith(f"{scheme}://") for u in found)


def test_scanstation_devices_lists_the_camera_backends(capsys):
    from capture.cli import main

    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[1]: line for line in out.splitlines() if line.startswith("camera")}
    assert set(rows) == {"oak://", "sim://"}
    assert "sim://camera" in out.split("camera     sim://")[1]
    assert "available" in rows["sim://"]
