"""The device exception tree. Each error is also the matching builtin: callers may catch either."""

from __future__ import annotations


class DeviceError(Exception):
    """Base of every device failure."""


class InvalidDeviceURL(DeviceError, ValueError):
    """A device URL that no backend understands, or with bad parameters."""


class DeviceNotFound(DeviceError, LookupError):
    """No device answers at the given address."""


class DeviceDisconnected(DeviceError, ConnectionError):
    """The device went away (cable pulled, USB reset, link error)."""


class DeviceTimeout(DeviceError, TimeoutError):
    """The device did not answer in time."""


class DriverUnavailable(DeviceError, ImportError):
    """The vendor SDK for a backend is not installed (e.g. `pip install scanstation[oak]`)."""


class FirmwareError(DeviceError):
    """The device's firmware refused a command; carries the firmware's own code and meaning."""

    def __init__(self, code: int | str, meaning: str, command: str | None = None):
        self.code = code
        self.meaning = meaning
        self.command = command
        where = f" (to {command!r})" if command else ""
        super().__init__(f"firmware error {code}: {meaning}{where}")


class FirmwareAlarm(FirmwareError):
    """The firmware raised an alarm and locked motion until it is cleared."""

    def __init__(self, code: int | str, meaning: str, command: str | None = None):
        super().__init__(code, meaning, command)
        self.args = (f"firmware alarm {code}: {meaning}",)


class HomingFailed(FirmwareAlarm):
    """The homing cycle failed (GRBL's ALARM:6–10); the message says what to check."""


class MoveAborted(DeviceError):
    """A move did not reach its target because it was stopped (`Turntable.stop`,
    `Turntable.emergency_stop`) or the firmware reset meanwhile. ``target`` is the angle it was
    going to; read ``angle`` for where the table stands."""

    def __init__(self, message: str, target: float | None = None):
        super().__init__(message)
        self.target = target
