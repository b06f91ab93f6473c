"""The working volume: a cylinder about the turntable axis, in the table frame (plain data)."""

from __future__ import annotations

from typing import NamedTuple


class Cylinder(NamedTuple):
    """Radius about the axis and height range above the plate, mm."""

    radius_mm: float
    z_min_mm: float
    z_max_mm: float
