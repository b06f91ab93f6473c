"""Request bodies of the API, and the checks that turn a scan request into something runnable.

Pydantic checks shapes and types (422 with the field named); `check_scan_request` then checks
meaning — a plan that can run, device URLs that a backend understands, an object the simulated
camera can load — so that a bad request fails at once with one line, never later in a thread.
"""

from __future__ import annotations

import os
import re
import urllib.parse
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from capture.plan import ScanPlan
from capture.station import is_simulated, station_urls
from drivers.registry import backend_class

from .auth import is_loopback
from .policy import DevicePolicy

#: scan ids the daemon makes: 16 lowercase hex digits (also what a path may contain)
SCAN_ID_PATTERN = r"^[0-9a-f]{16}$"
MESH_FORMATS = ("ply", "obj", "stl", "glb")
MAX_URL = 512


class ScanRequest(BaseModel):
    """POST /api/v1/scans: a plan (`capture.plan.ScanPlan` as JSON; missing fields take their
    defaults) and device URLs; none → the simulated station, whose camera shows ``object``
    (a built-in name, or a mesh file in the operator's ``--object-dir``)."""

    model_config = ConfigDict(extra="forbid")

    plan: dict[str, Any] = Field(default_factory=dict, description="ScanPlan fields")
    camera_url: str | None = Field(default=None, max_length=MAX_URL, examples=["oak://"])
    turntable_url: str | None = Field(
        default=None, max_length=MAX_URL, examples=["grbl:///dev/ttyUSB0"]
    )
    object: str | None = Field(default=None, min_length=1, max_length=1024, examples=["vase"])


class RefineRequest(BaseModel):
    """POST …/refine: new spline smoothing λ and/or boundary depth (missing: keep the current)."""

    model_config = ConfigDict(extra="forbid")

    # strict: a JSON true or "2" is no λ or depth (lax pydantic took true for λ = 1)
    lam: float | None = Field(default=None, ge=0, le=1e6, allow_inf_nan=False, strict=True)
    depth: int | None = Field(default=None, ge=1, le=16, strict=True)


MeshFormat = Literal["ply", "obj", "stl", "glb"]


def check_scan_request(request: ScanRequest, policy: DevicePolicy) -> tuple[ScanPlan, str | None]:
    """(the validated plan, the object to load: a built-in name or a checked file path);
    raises ValueError (one line) for anything that cannot run or that the operator does not
    allow (`capture.daemon.policy`).

    Device URLs must name a known backend with valid parameters (the device is built, never
    opened here: that happens in the scan's process); an object file is checked by size and
    type, and parsed only by the scan's process.
    """
    plan = ScanPlan.from_dict(request.plan)
    for kind, url in (("camera", request.camera_url), ("turntable", request.turntable_url)):
        if url is not None:
            backend_class(kind, url).from_url(url)
            policy.check_url(kind, url)
    obj = policy.resolve_object(request.object)
    if request.object is not None:  # a real camera has no object to show
        station_urls(request.camera_url, request.turntable_url, request.object)
    return plan, obj


def device_keys(camera_url: str | None, turntable_url: str | None) -> list[str]:
    """What a scan holds while it runs: each device as its driver opens it, without options.

    A camera is its URL's scheme, host and path. A GRBL turntable is the port its driver opens
    (``serial:`` and the device's real path, or a pyserial URL's scheme, host and port with every
    loopback name as ``localhost``):
    two URLs that reach one device hold one key. A simulated device is one per simulated
    station, so its key names the station; a simulated URL without a station (or no URL at
    all) gets a fresh station of its own and holds nothing.
    """
    keys = []
    for kind, url in (("camera", camera_url), ("turntable", turntable_url)):
        if url is None:
            continue
        parts = urllib.parse.urlsplit(url)
        if is_simulated(url):
            station = urllib.parse.parse_qs(parts.query).get("station")
            if not station:
                continue
            keys.append(f"sim://{kind}?station={station[-1]}")
        elif kind == "turntable":  # the port as its driver reads it from the URL
            keys.append(_port_key(backend_class(kind, url).from_url(url).port))
        else:
            keys.append(urllib.parse.urlunsplit(parts._replace(query="", fragment="")))
    return keys


def _port_key(port: str) -> str:
    """The key of a serial port a GRBL turntable opens: a device path (its real path), or a
    pyserial URL (``socket://host:port``, loopback names as ``localhost``)."""
    if "://" not in port:
        return f"serial:{os.path.realpath(port) if port.startswith('/') else port.upper()}"
    parts = urllib.parse.urlsplit(port)
    host = (parts.hostname or "").lower()
    host = "localhost" if is_loopback(host) else host
    try:
        number = parts.port
    except ValueError:
        number = None
    return f"{parts.scheme.lower()}://{host}:{number}{parts.path}"


def is_scan_id(text: str) -> bool:
    return re.fullmatch(SCAN_ID_PATTERN, text) is not None
