"""depthai messages ↔ ScanStation types, on the host (no device needed): depth ImgFrames and
message groups → `Frame`, depth images → ImgFrames, intrinsics from a CalibrationHandler or a
frame, depthai errors → `drivers.errors`, and depthai's own PointCloud node run on the host.
Imported only through `drivers.oak` (the registry loads it lazily)."""

from __future__ import annotations

import contextlib
import datetime
import os

import numpy as np

os.environ.setdefault("DEPTHAI_LEVEL", "error")  # no USB warning on every import; env overrides
import depthai as dai  # noqa: E402

from .base import Frame  # noqa: E402
from .errors import DeviceDisconnected, DeviceError, DeviceNotFound, DeviceTimeout  # noqa: E402

RIGHT = dai.CameraBoardSocket.CAM_C
_LINK_MARKERS = ("X_LINK", "XLINK", "Communication exception", "device was disconnected")
#: what depthai raises: RuntimeError (and its XLinkError), QueueException for a closed queue
VENDOR_ERRORS = (RuntimeError, dai.MessageQueue.QueueException)


def vendor_error(exc: BaseException, what: str) -> DeviceError:
    """Our exception for a depthai failure during ``what`` (raise it ``from exc``)."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if isinstance(exc, (dai.XLinkError, dai.MessageQueue.QueueException)) or any(
        marker.lower() in text.lower() for marker in _LINK_MARKERS
    ):
        return DeviceDisconnected(f"{what}: OAK link lost ({text})")
    if "no available devices" in text.lower() or "cannot find any device" in text.lower():
        return DeviceNotFound(f"{what}: {text}")
    return DeviceError(f"{what}: {text}")


@contextlib.contextmanager
def vendor_errors(what: str):
    """Re-raise depthai's errors inside the block as `drivers.errors` types."""
    try:
        yield
    except VENDOR_ERRORS as exc:
        raise vendor_error(exc, what) from exc


def frame_from_message(message) -> Frame:
    """A `Frame` from what the pipeline sends: a RAW16 depth ImgFrame (mm), or a MessageGroup
    of "depth" and its synced RGB888i "color" frame.

    Frame.depth : (H, W) uint16 mm (a copy); color : (H, W, 3) uint8 or None;
    timestamp : the depth frame's host-synced time, s; sequence : the device's frame number.
    """
    color = None
    if isinstance(message, dai.MessageGroup):
        names = set(message.getMessageNames())
        if "depth" not in names:
            raise DeviceError(f"message group without depth (has {', '.join(sorted(names))})")
        color = message["color"] if "color" in names else None
        message = message["depth"]
    if not isinstance(message, dai.ImgFrame) or message.getType() != dai.ImgFrame.Type.RAW16:
        kind = message.getType().name if isinstance(message, dai.ImgFrame) else type(message)
        raise DeviceError(f"expected a RAW16 depth frame, got {kind}")
    depth = np.array(message.getFrame(), dtype=np.uint16, copy=True)
    if depth.shape != (message.getHeight(), message.getWidth()):
        raise DeviceError(f"depth frame has shape {depth.shape}, its header says "
                          f"{message.getHeight()}×{message.getWidth()}")
    rgb = None
    if color is not None:
        rgb = np.array(color.getFrame(), dtype=np.uint8, copy=True)
        if rgb.shape != (*depth.shape, 3):
            raise DeviceError(f"colour frame has shape {rgb.shape}, depth {depth.shape}")
    return Frame(depth=depth, timestamp=message.getTimestamp().total_seconds(), color=rgb,
                 sequence=message.getSequenceNum())


def img_from_depth(depth, intrinsics, timestamp: float = 0.0, sequence: int = 0,
                   socket=RIGHT) -> dai.ImgFrame:
    """A depthai RAW16 ImgFrame of a (H, W) uint16 mm depth image seen through ``intrinsics``
    (3, 3) by the camera at ``socket`` (what the device sends; used to feed host-side nodes)."""
    depth = np.ascontiguousarray(depth, dtype=np.uint16)
    height, width = depth.shape
    frame = dai.ImgFrame()
    frame.setCvFrame(depth, dai.ImgFrame.Type.RAW16)
    extrinsics = dai.Extrinsics(np.eye(4).tolist(), socket, dai.LengthUnit.MILLIMETER)
    frame.setTransformation(dai.ImgTransformation(
        width, height, np.asarray(intrinsics, dtype=float).tolist(), dai.CameraModel.Perspective,
        [0.0] * 14, extrinsics))
    frame.setTimestamp(datetime.timedelta(seconds=timestamp))
    frame.setSequenceNum(sequence)
    return frame


def intrinsics_from_calibration(calibration: dai.CalibrationHandler, socket, width: int,
                                height: int) -> np.ndarray:
    """(3, 3) pinhole matrix of the camera at ``socket`` scaled to a width × height output."""
    if not calibration.hasCameraCalibration(socket):
        raise DeviceError(f"the OAK's calibration has no intrinsics for {socket.name}")
    with vendor_errors(f"reading the intrinsics of {socket.name}"):
        k = np.array(calibration.getCameraIntrinsics(socket, width, height), dtype=np.float64)
    return k


def intrinsics_of(message) -> np.ndarray | None:
    """(3, 3) pinhole matrix a depth ImgFrame (or MessageGroup) carries after the device's
    crops and scales, or None when it has no valid transformation."""
    if isinstance(message, dai.MessageGroup):
        message = message["depth"]
    transformation = message.getTransformation()
    if not transformation.isValid():
        return None
    k = np.array(transformation.getIntrinsicMatrix(), dtype=np.float64)
    return k if k.shape == (3, 3) and k[0, 0] > 0 and k[1, 1] > 0 else None


def host_point_cloud(depth, intrinsics, timeout: float = 5.0) -> np.ndarray:
    """(n, 3) float32 points, mm, of a (H, W) uint16 depth image computed by depthai's own
    PointCloud node in a host-only pipeline (no device needed), for checking and replay."""
    with vendor_errors("host point cloud"), dai.Pipeline(False) as pipeline:
        node = pipeline.create(dai.node.PointCloud)
        node.sync.setRunOnHost(True)
        node.setRunOnHost(True)
        to_node = node.inputDepth.createInputQueue()
        from_node = node.outputPointCloud.createOutputQueue()
        pipeline.start()
        to_node.send(img_from_depth(depth, intrinsics))
        cloud = from_node.get(datetime.timedelta(seconds=timeout))
        pipeline.stop()
    if cloud is None:
        raise DeviceTimeout(f"host point cloud: no result within {timeout} s")
    points = np.asarray(cloud.getPoints(), dtype=np.float32).reshape(-1, 3)
    return points[points[:, 2] > 0]
