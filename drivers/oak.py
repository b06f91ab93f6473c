"""``oak://``: Luxonis OAK stereo depth cameras through depthai 3.x.

    oak://                      the first device found
    oak://<device id or IP>     a given device (MXID / device id, or a PoE camera's address)
    oak://?width=640&height=400&fps=30&align=auto&pointcloud=0&timeout=5

Pipeline: left/right mono cameras (CAM_B, CAM_C) → StereoDepth (subpixel, left-right check)
→ depth (uint16 mm) aligned to the colour camera (CAM_A) when present (``align=auto|color``),
else to the right camera (``align=right``), → host queue; with ``pointcloud=1`` also the
on-device PointCloud node (`OakCamera.grab_points`). Intrinsics: those the first depth frame
carries (exact after the device's crops and scales), else the device calibration's for the
aligned camera at the output size. ``grab`` returns the first frame captured after the call.
depthai errors are re-raised as `drivers.errors` types with the vendor error as cause: link
loss (X_LINK…) → DeviceDisconnected. Host-side conversions live in `drivers.oak_messages`.
"""

from __future__ import annotations

import contextlib
import datetime
import ipaddress
import logging
import time
import urllib.parse

import numpy as np

from .base import DepthCamera, Frame
from .errors import DeviceError, DeviceNotFound, DeviceTimeout, InvalidDeviceURL
from .oak_messages import (
    VENDOR_ERRORS,
    dai,  # depthai, imported there once (with its log level set)
    frame_from_message,
    intrinsics_from_calibration,
    intrinsics_of,
    vendor_errors,
)

log = logging.getLogger(__name__)

LEFT, RIGHT, COLOR = (dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C,
                      dai.CameraBoardSocket.CAM_A)
#: option -> (type, default)
OPTIONS: dict[str, tuple[type, object]] = {
    "width": (int, 640), "height": (int, 400), "fps": (float, 30.0), "align": (str, "auto"),
    "pointcloud": (int, 0), "timeout": (float, 5.0),
}
_ALIGN = ("auto", "color", "right")
_QUEUE_SIZE = 2  # host queues keep only the newest frames (grab wants a fresh one)


def parse_url(url: str, **overrides) -> tuple[str, dict]:
    """(device id or address, "" for the first device; options) of an ``oak://`` URL."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme != "oak":
        raise InvalidDeviceURL(f"not an OAK camera URL: {url!r}")
    given = {k: v[-1] for k, v in urllib.parse.parse_qs(parts.query).items()}
    given.update({k: v for k, v in overrides.items() if v is not None})  # None: default
    unknown = sorted(set(given) - set(OPTIONS))
    if unknown:
        raise InvalidDeviceURL(f"unknown parameter(s) {', '.join(unknown)} in {url!r}")
    options = {}
    for key, (kind, default) in OPTIONS.items():
        try:
            options[key] = kind(given.get(key, default))
        except (TypeError, ValueError) as exc:
            raise InvalidDeviceURL(f"parameter {key}={given[key]!r} is not a {kind.__name__} "
                                   f"in {url!r}") from exc
    if options["align"] not in _ALIGN:
        raise InvalidDeviceURL(f"align must be one of {', '.join(_ALIGN)} in {url!r}")
    if options["width"] < 1 or options["height"] < 1 or options["fps"] <= 0:
        raise InvalidDeviceURL(f"width, height and fps must be positive in {url!r}")
    return (parts.netloc + parts.path).strip("/"), options


def _is_address(device_id: str) -> bool:
    try:
        ipaddress.ip_address(device_id)
    except ValueError:
        return False
    return True


class OakCamera(DepthCamera):
    """A Luxonis OAK stereo camera giving depth in mm (see the module docstring for URLs)."""

    schemes = ("oak",)

    def __init__(self, url: str = "oak://", **options):
        super().__init__(url)
        self.device_id, self.options = parse_url(url, **options)
        self.shape = (self.options["height"], self.options["width"])
        self._stack: contextlib.ExitStack | None = None
        self._pipeline = None
        self._frames_queue = self._points_queue = None
        self._intrinsics: np.ndarray | None = None
        self.aligned_to = None  # the camera socket the depth is aligned to, once open

    @classmethod
    def from_url(cls, url: str, **options) -> OakCamera:
        return cls(url, **options)

    @classmethod
    def discover(cls) -> list[str]:
        """``oak://<device id>`` of every OAK that depthai sees (USB and network; ~0.5 s)."""
        with vendor_errors("OAK discovery"):
            return [f"oak://{info.deviceId}" for info in dai.Device.getAllAvailableDevices()]

    @property
    def intrinsics(self) -> np.ndarray:
        if self._intrinsics is None:
            raise DeviceError(f"{self.url}: intrinsics are known once the camera is open")
        return self._intrinsics.copy()

    def _device_info(self) -> dai.DeviceInfo:
        """The device to open; `DeviceNotFound` at once when depthai sees none that matches."""
        if _is_address(self.device_id):
            return dai.DeviceInfo(self.device_id)  # a PoE camera may not answer broadcasts
        with vendor_errors("OAK discovery"):
            found = dai.Device.getAllAvailableDevices()
        for info in found:
            if not self.device_id or self.device_id in (info.deviceId, info.name):
                return info
        if not found:
            raise DeviceNotFound(f"{self.url}: no OAK device found (plugged in? in a container, "
                                 "is USB passed through?)")
        seen = ", ".join(info.deviceId for info in found)
        raise DeviceNotFound(f"{self.url}: no OAK device {self.device_id} (found: {seen})")

    def _open(self) -> None:
        info = self._device_info()
        stack = contextlib.ExitStack()
        try:
            with vendor_errors(f"{self.url}: opening"):
                device = stack.enter_context(dai.Device(info))
                self._pipeline = stack.enter_context(dai.Pipeline(device))
                calibration = device.readCalibration()
                self._build(self._pipeline, set(device.getConnectedCameras()))
                self._pipeline.start()
            first = self._receive(self._frames_queue, self.options["timeout"], "first frame")
            width, height = self.options["width"], self.options["height"]
            carried = intrinsics_of(first)  # exact after the device's crops and scales
            self._intrinsics = carried if carried is not None else intrinsics_from_calibration(
                calibration, self.aligned_to, width, height)
        except BaseException:
            self._release(stack)
            raise
        self._stack = stack
        log.info("opened %s (%s), depth aligned to %s", self.url, info.deviceId,
                 self.aligned_to.name)

    def _build(self, pipeline: dai.Pipeline, sockets: set) -> None:
        """Create the nodes and host queues of the depth pipeline."""
        if not {LEFT, RIGHT} <= sockets:
            raise DeviceError(f"{self.url}: not a stereo OAK (cameras: "
                              f"{', '.join(s.name for s in sockets)})")
        if self.options["align"] == "color" and COLOR not in sockets:
            raise DeviceError(f"{self.url}: align=color but the device has no colour camera")
        use_color = self.options["align"] != "right" and COLOR in sockets
        size, fps = (self.options["width"], self.options["height"]), self.options["fps"]
        left = pipeline.create(dai.node.Camera).build(LEFT)
        right = pipeline.create(dai.node.Camera).build(RIGHT)
        stereo = pipeline.create(dai.node.StereoDepth)
        left.requestOutput(size, fps=fps).link(stereo.left)
        right.requestOutput(size, fps=fps).link(stereo.right)
        stereo.setRectification(True)
        stereo.setSubpixel(True)
        stereo.setLeftRightCheck(True)
        self.aligned_to = COLOR if use_color else RIGHT
        stereo.setDepthAlign(self.aligned_to)
        stereo.setOutputSize(*size)
        if use_color:  # pair each depth frame with its colour frame on the device
            color = pipeline.create(dai.node.Camera).build(COLOR)
            sync = pipeline.create(dai.node.Sync)
            sync.setSyncThreshold(datetime.timedelta(seconds=0.5 / fps))
            stereo.depth.link(sync.inputs["depth"])
            rgb = color.requestOutput(size, dai.ImgFrame.Type.RGB888i, fps=fps)
            rgb.link(sync.inputs["color"])
            self._frames_queue = sync.out.createOutputQueue(_QUEUE_SIZE, False)
        else:
            self._frames_queue = stereo.depth.createOutputQueue(_QUEUE_SIZE, False)
        self._points_queue = None
        if self.options["pointcloud"]:
            cloud = pipeline.create(dai.node.PointCloud)
            stereo.depth.link(cloud.inputDepth)
            self._points_queue = cloud.outputPointCloud.createOutputQueue(_QUEUE_SIZE, False)

    def _close(self) -> None:
        stack, self._stack = self._stack, None
        if stack is not None:
            self._release(stack)

    def _release(self, stack: contextlib.ExitStack) -> None:
        """Stop the pipeline and close the device; never raises (the link may be gone)."""
        try:
            pipeline = getattr(self, "_pipeline", None)
            if pipeline is not None and pipeline.isRunning():
                pipeline.stop()
            stack.close()
        except VENDOR_ERRORS as exc:
            log.debug("%s: closing after an error: %s", self.url, exc)
        self._pipeline = None

    def _receive(self, queue, seconds: float, what: str):
        """The next message of a host queue, or `DeviceTimeout` after ``seconds``."""
        with vendor_errors(f"{self.url}: {what}"):
            message = queue.get(datetime.timedelta(seconds=seconds))
        if message is None:
            raise DeviceTimeout(f"{self.url}: no {what} within {seconds} s")
        return message

    def _next(self, queue_name: str, timeout: float | None, what: str):
        """The first message captured after this call (older queued ones are skipped, e.g. those
        from while the table was still moving); `DeviceTimeout` after ``timeout`` s."""
        if not self.is_open:
            raise DeviceError(f"{self.url}: camera is not open")
        queue = getattr(self, queue_name)
        if queue is None:
            raise DeviceError(f"{self.url}: open with pointcloud=1 to grab point clouds")
        since = dai.Clock.now()  # the host-synced clock of the frames' timestamps
        seconds = self.options["timeout"] if timeout is None else timeout
        deadline = time.monotonic() + seconds
        while True:
            left = max(deadline - time.monotonic(), 0.0)
            with vendor_errors(f"{self.url}: {what}"):
                message = queue.get(datetime.timedelta(seconds=left))
            if message is None:
                raise DeviceTimeout(f"{self.url}: no {what} within {seconds} s")
            stamped = message["depth"] if isinstance(message, dai.MessageGroup) else message
            if stamped.getTimestamp() >= since:
                return message

    def grab(self, timeout: float | None = None) -> Frame:
        """The next depth frame (with colour when aligned to the colour camera)."""
        message = self._next("_frames_queue", timeout, "depth frame")
        return frame_from_message(message)

    def grab_points(self, timeout: float | None = None) -> np.ndarray:
        """(n, 3) float32 points, mm, in the aligned camera's frame, from the device's PointCloud
        node (needs ``pointcloud=1``)."""
        cloud = self._next("_points_queue", timeout, "point cloud")
        points = np.asarray(cloud.getPoints(), dtype=np.float32).reshape(-1, 3)
        return points[points[:, 2] > 0]
