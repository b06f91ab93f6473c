"""Simulated stations: the devices of one station name share a turntable, so the simulated camera
renders what the simulated turntable's current angle shows (ophyd's detector-reads-motor)."""

from __future__ import annotations

import threading
from typing import Protocol


class AngleSource(Protocol):
    def position_degrees(self) -> float:
        """Current table angle in degrees, as the simulated motion has it right now."""


class SimStation:
    """The shared state of one simulated station."""

    def __init__(self, name: str):
        self.name = name
        self.angle_source: AngleSource | None = None

    def angle_degrees(self) -> float:
        """The turntable's true angle now (0 when no simulated turntable is attached)."""
        return 0.0 if self.angle_source is None else float(self.angle_source.position_degrees())


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
