"""Device drivers: one small base per device kind, backends picked by URL scheme."""

from .base import DepthCamera, Device, Frame, Turntable
from .errors import (
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceTimeout,
    DriverUnavailable,
    FirmwareAlarm,
    FirmwareError,
    HomingFailed,
    InvalidDeviceURL,
    MoveAborted,
)
from .registry import list_devices, open_camera, open_turntable

__all__ = [
    "DepthCamera",
    "Device",
    "DeviceDisconnected",
    "DeviceError",
    "DeviceNotFound",
    "DeviceTimeout",
    "DriverUnavailable",
    "FirmwareAlarm",
    "FirmwareError",
    "Frame",
    "HomingFailed",
    "InvalidDeviceURL",
    "MoveAborted",
    "Turntable",
    "list_devices",
    "open_camera",
    "open_turntable",
]
