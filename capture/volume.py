"""The working volume: a cylinder about the turntable axis, in the table frame (plain data)."""

from __future__ import annotations

from typing import NamedTuple


class Cylinder(NamedTuple):
    """Radius about the axis and height range above the plate, mm."""

    radius_mm: float
    z_min_mm: float
    z_max_mm: float

    def describe(self) -> str:
        """In words, for messages: "radius 110 mm, 3-250 mm above the plate"."""
        return (f"radius {self.radius_mm:g} mm, {self.z_min_mm:g}-{self.z_max_mm:g} mm above "
                f"the plate")
