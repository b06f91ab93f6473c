"""Simulated stations: the devices of one station name share a turntable, so the simulated camera
renders what the simulated turntable's current angle shows (ophyd's detector-reads-motor)."""

from __future__ import annotations

import threading
from typing import Protocol


class AngleSource(Protocol):
    def position_degrees(self, axis: str = "X") -> float:
        """Current angle of the table's ``axis`` in degrees, as the simulated motion has it."""


class SimStation:
    """The shared state of one simulated station."""

    def __init__(self, name: str):
        self.name = name
        self.angle_source: AngleSource | None = None
        self.angle_axis = "X"  # the firmware axis the turntable driver turns

    def angle_degrees(self) -> float:
        """The turntable's true angle now (0 when no simulated turntable is attached)."""
        if self.angle_source is None:
            return 0.0
        return float(self.angle_source.position_degrees(self.angle_axis))


_stations: dict[str, SimStation] = {}
_lock = threading.Lock()


def get_station(name: str = "default") -> SimStation:
    """The station called ``name``, created on first use."""
    with _lock:
        if name not in _stations:
            _stations[name] = SimStation(name)
        return _stations[name]


def reset_stations() -> None:
    """Forget every station (tests)."""
    with _lock:
        _stations.clear()
