"""One small base per device kind. Backends implement the `_`-prefixed hooks; the base owns the
context manager and a close that is safe to repeat."""

from __future__ import annotations

import abc
import dataclasses
import threading
from typing import ClassVar

import numpy as np


class Device(abc.ABC):
    """Common life cycle: ``open()`` once, ``close()`` any number of times, or use ``with``."""

    #: URL scheme(s) that select this backend, set by subclasses.
    schemes: ClassVar[tuple[str, ...]] = ()

    def __init__(self, url: str = ""):
        self.url = url
        self._is_open = False
        self._close_lock = threading.Lock()

    @classmethod
    @abc.abstractmethod
    def from_url(cls, url: str, **options) -> Device:
        """Build an unopened device from its URL (query parameters become options)."""

    @classmethod
    def discover(cls) -> list[str]:
        """URLs of the devices of this backend that can be seen now (may be empty)."""
        return []

    @property
    def is_open(self) -> bool:
        return self._is_open

    def open(self) -> Device:
        if not self._is_open:
            self._open()
            self._is_open = True
        return self

    def close(self) -> None:
        with self._close_lock:
            if not self._is_open:
                return
            self._is_open = False
        self._close()

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "open" if self._is_open else "closed"
        return f"<{type(self).__name__} {self.url!r} {state}>"

    @abc.abstractmethod
    def _open(self) -> None: ...

    @abc.abstractmethod
    def _close(self) -> None: ...


class Turntable(Device):
    """A rotary stage. Angles in degrees; moves return when the table is still, and raise
    `MoveAborted` when a stop cut them short."""

    @abc.abstractmethod
    def home(self) -> None:
        """Make the current position the zero angle (or run the device's homing cycle)."""

    @abc.abstractmethod
    def move_to(self, degrees: float) -> None:
        """Rotate to an absolute angle and return once still."""

    def move_by(self, degrees: float) -> None:
        """Rotate by a relative angle and return once still."""
        self.move_to(self.angle + degrees)

    @property
    @abc.abstractmethod
    def angle(self) -> float:
        """Current angle in degrees, as reported by the device."""

    @abc.abstractmethod
    def wait_until_still(self, timeout: float | None = None) -> None:
        """Block until the table stops moving; raise `DeviceTimeout` after ``timeout`` seconds."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop any motion with a controlled deceleration; the angle stays valid. A move
        waiting in another thread raises `MoveAborted`."""

    def emergency_stop(self) -> None:
        """Stop at once, when speed matters more than position: the angle may be lost
        (``referenced`` becomes False until `home`). Backends that can stop harder override it."""
        self.stop()

    @property
    def referenced(self) -> bool:
        """True while the angle is known to match the table (no stop has lost steps, homed if
        the device homes)."""
        return True


@dataclasses.dataclass(frozen=True)
class Frame:
    """One depth frame.

    depth : (H, W) uint16, millimetres, 0 where the camera has no measurement.
    color : (H, W, 3) uint8 RGB aligned to depth, or None.
    timestamp : seconds (device clock when known, else host monotonic clock).
    """

    depth: np.ndarray
    timestamp: float
    color: np.ndarray | None = None
    sequence: int = 0

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape


class DepthCamera(Device):
    """A depth camera giving frames in millimetres with pinhole intrinsics."""

    @property
    @abc.abstractmethod
    def intrinsics(self) -> np.ndarray:
        """(3, 3) float camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels."""

    @abc.abstractmethod
    def grab(self, timeout: float | None = None) -> Frame:
        """Wait for and return the next frame."""
