"""Backends chosen by URL scheme from a lazily imported registry (importing never loads an SDK)."""

from __future__ import annotations

import importlib
import urllib.parse

from .base import DepthCamera, Device, Turntable
from .errors import DriverUnavailable, InvalidDeviceURL

#: kind -> scheme -> (module, class). `sim` backends live in the `sim` package (first-class).
BACKENDS: dict[str, dict[str, tuple[str, str]]] = {
    "turntable": {
        "grbl": ("drivers.grbl", "GrblTurntable"),
        "socket": ("drivers.grbl", "GrblTurntable"),
        "rfc2217": ("drivers.grbl", "GrblTurntable"),
        "sim": ("sim.turntable", "SimTurntable"),
    },
    "camera": {
        "oak": ("drivers.oak", "OakCamera"),
        "sim": ("sim.camera", "SimCamera"),
    },
}


def backend_class(kind: str, url: str) -> type[Device]:
    """The class that handles ``url`` for a device ``kind`` ("turntable" or "camera")."""
    scheme = urllib.parse.urlsplit(url).scheme
    table = BACKENDS[kind]
    if scheme not in table:
        known = ", ".join(f"{s}://" for s in table)
        raise InvalidDeviceURL(f"no {kind} backend for {url!r} (known: {known})")
    module_name, class_name = table[scheme]
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DriverUnavailable(f"{kind} backend {scheme}:// is unavailable: {exc}") from exc
    return getattr(module, class_name)


def open_turntable(url: str, **options) -> Turntable:
    """Open the turntable at ``url``, e.g. ``grbl:///dev/ttyUSB0?baud=115200`` or ``sim://turntable``."""
    device = backend_class("turntable", url).from_url(url, **options)
    return device.open()


def open_camera(url: str, **options) -> DepthCamera:
    """Open the depth camera at ``url``, e.g. ``oak://`` or ``sim://camera?object=vase``."""
    device = backend_class("camera", url).from_url(url, **options)
    return device.open()


def list_devices() -> list[tuple[str, str, str, list[str]]]:
    """Every backend as (kind, scheme, status, visible device URLs); never raises."""
    rows = []
    seen: set[tuple[str, str, str]] = set()
    for kind, table in BACKENDS.items():
        for scheme, (module_name, class_name) in table.items():
            try:
                cls = backend_class(kind, f"{scheme}://")
            except DriverUnavailable as exc:
                rows.append((kind, scheme, f"unavailable: {exc.__cause__}", []))
                continue
            key = (kind, module_name, class_name)
            if key in seen:
                rows.append((kind, scheme, "available", []))
                continue
            seen.add(key)
            try:
                urls = cls.discover()
                status = "available"
            except Exception as exc:  # discovery must never break the listing
                urls, status = [], f"discovery failed: {exc}"
            rows.append((kind, scheme, status, urls))
    return rows
