"""What an API request may name on the station: device addresses and object files.

The operator decides, not the request. By default a scan may use serial ports (``/dev/…``,
``COMn``), loopback addresses (a ser2net or simulator on this machine), OAK cameras by device id
and simulated devices; any other address (``socket://10.0.0.5:23``, ``oak://192.168.1.44``,
``grbl:///srv/fifo``) must be allowed with ``scanstation serve --allow-device URL``. Device
timeouts given in a URL are bounded (a request cannot make a scan wait on a device for hours),
and so is a simulated camera's image.

An ``object`` (the simulated camera's mesh) is a built-in name, or a file inside the folder the
operator gave with ``--object-dir``; such a file is checked cheaply here (size, type, first
bytes) and parsed only in the scan's own process. Refusals never say whether a path outside
that folder exists.
"""

from __future__ import annotations

import ipaddress
import math
import os
import re
import urllib.parse
from pathlib import Path

from .auth import is_loopback
from .errors import InvalidRequest

MAX_DEVICE_TIMEOUT_S = 30.0
#: device URL parameters that are seconds to wait on a device
TIMEOUT_PARAMETERS = ("timeout", "link_timeout", "poll")
DEFAULT_MAX_OBJECT_BYTES = 256 << 20
#: The largest side of a simulated camera's image a request may ask for (an OAK's largest
#: sensor is 4056 × 3040)
MAX_SIM_PIXELS = 4096
MESH_SUFFIXES = (".stl", ".ply", ".obj", ".off", ".glb")
_MAGIC = {".ply": b"ply", ".glb": b"glTF"}
_OAK_DEVICE_ID = re.compile(r"^[0-9A-Fa-f]{8,40}$")
_WINDOWS_PORT = re.compile(r"^COM\d{1,3}$", re.IGNORECASE)
#: pyserial URL handlers that reach a host (checked) or nothing outside the process
_NETWORK_SCHEMES = ("socket", "rfc2217")
_HARMLESS_SCHEMES = ("loop",)


class Refused(InvalidRequest):
    """A device or file that this daemon's operator did not allow (422)."""


def _key(url: str) -> tuple[str, str, int | None, str]:
    parts = urllib.parse.urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        port = -1
    return parts.scheme.lower(), (parts.hostname or "").lower(), port, parts.path


class DevicePolicy:
    """The operator's rules. ``allow``: device URLs (options ignored; no port = any port) that
    requests may use beyond the defaults; ``object_dir``: the folder of mesh files requests may
    name (None: built-in objects only)."""

    def __init__(self, allow=(), object_dir: str | Path | None = None,
                 max_object_bytes: int = DEFAULT_MAX_OBJECT_BYTES,
                 max_timeout_s: float = MAX_DEVICE_TIMEOUT_S):
        self.allow = [_key(url) for url in allow]
        bad = [url for url, key in zip(allow, self.allow, strict=True) if not key[0]]
        if bad:
            raise ValueError(f"--allow-device needs a URL with a scheme, got {bad[0]!r}")
        self.object_dir = None if object_dir is None else Path(object_dir).resolve()
        self.max_object_bytes = max_object_bytes
        self.max_timeout_s = max_timeout_s

    # -- devices ---------------------------------------------------------------------------------
    def check_url(self, kind: str, url: str) -> None:
        """`Refused` unless ``url`` (a device of ``kind``) is allowed and its timeouts bounded."""
        parts = urllib.parse.urlsplit(url)
        query = urllib.parse.parse_qs(parts.query, keep_blank_values=True)
        self._check_timeouts(url, query)
        scheme = parts.scheme.lower()
        if scheme == "sim":
            return _check_simulated(kind, url, query)
        if self._listed(url):
            return
        if scheme == "oak":
            netloc = parts.netloc
            usb_port = re.fullmatch(r"[\d.]+", netloc) and not _is_address(netloc)
            ok = not netloc or _OAK_DEVICE_ID.match(netloc) or usb_port or \
                is_loopback(parts.hostname or "")
        elif scheme == "grbl":
            port = (query.get("port") or [parts.netloc + parts.path])[-1]
            ok = self._port_ok(port)
        elif scheme in _NETWORK_SCHEMES:
            ok = is_loopback(parts.hostname or "")
        else:
            return  # no such backend: the registry says so
        if not ok:
            raise Refused(f"{kind} {url!r} is not on this machine or a serial port: the operator "
                          "allows other devices with `scanstation serve --allow-device URL`")

    def _port_ok(self, port: str) -> bool:
        """A GRBL port: a serial device, or a pyserial URL that is itself allowed."""
        if "://" in port:
            inner = urllib.parse.urlsplit(port)
            query = urllib.parse.parse_qs(inner.query, keep_blank_values=True)
            self._check_timeouts(port, query)
            scheme = inner.scheme.lower()
            if scheme in _NETWORK_SCHEMES:
                return is_loopback(inner.hostname or "") or self._listed(port)
            return scheme in _HARMLESS_SCHEMES or self._listed(port)
        if _WINDOWS_PORT.match(port):
            return True
        normal = os.path.normpath(port) if port else ""
        return (normal == port and normal.startswith("/dev/")) or self._listed(f"grbl://{port}")

    def _listed(self, url: str) -> bool:
        scheme, host, port, path = _key(url)
        for a_scheme, a_host, a_port, a_path in self.allow:
            if (a_scheme, a_host) == (scheme, host) and a_port in (None, port) and \
                    (not a_path or a_path == path):
                return True
        return False

    def _check_timeouts(self, url: str, query: dict[str, list[str]]) -> None:
        for name in TIMEOUT_PARAMETERS:
            for raw in query.get(name, []):
                try:
                    value = float(raw)
                except ValueError:
                    continue  # not a number: the driver names it
                if not (math.isfinite(value) and value <= self.max_timeout_s):
                    raise Refused(f"{name}={raw[:20]} in a device URL is over the daemon's "
                                  f"maximum of {self.max_timeout_s:g} s")

    # -- object files ----------------------------------------------------------------------------
    def resolve_object(self, name: str | None) -> str | None:
        """A built-in object's name, or the checked absolute path of a file in the object
        folder; `Refused` otherwise (one line, the same whether an outside path exists)."""
        from sim.objects import BUILT_IN

        if name is None or name in BUILT_IN:
            return name
        known = ", ".join(BUILT_IN)
        if self.object_dir is None:
            raise Refused(f"object {name!r} is not a built-in object ({known}); mesh files "
                          "need the operator's `scanstation serve --object-dir DIR`")
        path = (self.object_dir / name).resolve()
        if not path.is_relative_to(self.object_dir) or not path.is_file():
            raise Refused(f"object {name!r} is neither a built-in object ({known}) nor a file "
                          "in the operator's object folder")
        suffix = path.suffix.lower()
        if suffix not in MESH_SUFFIXES:
            raise Refused(f"object {name!r}: not a mesh file type (known: "
                          f"{', '.join(MESH_SUFFIXES)})")
        size = path.stat().st_size
        if size > self.max_object_bytes:
            raise Refused(f"object {name!r}: {size / 2**20:.0f} MiB, larger than the daemon's "
                          f"limit of {self.max_object_bytes / 2**20:g} MiB")
        magic = _MAGIC.get(suffix)
        if magic is not None:
            with open(path, "rb") as file:
                if not file.read(len(magic)) == magic:
                    raise Refused(f"object {name!r}: not a {suffix[1:].upper()} file (it does "
                                  f"not start with {magic.decode()!r})")
        return str(path)


def _check_simulated(kind: str, url: str, query: dict[str, list[str]]) -> None:
    """`Refused` for what a simulated device URL may not ask of this machine: an object file
    (named by the request's ``object``, which `DevicePolicy.resolve_object` checks) or a camera
    image over `MAX_SIM_PIXELS` a side (the scan's process holds several arrays of its size)."""
    if kind == "camera" and "object" in query:
        raise Refused("the simulated camera's object goes in the request's `object` field "
                      f"(checked against the operator's object folder), not in its URL {url!r}")
    for name in ("width", "height"):
        for raw in query.get(name, []):
            try:
                value = float(raw)
            except ValueError:
                continue  # not a number: the simulated camera names it
            if not value <= MAX_SIM_PIXELS:
                raise Refused(f"{name}={raw[:20]} in a simulated camera's URL is over the "
                              f"daemon's maximum of {MAX_SIM_PIXELS} pixels")


def _is_address(text: str) -> bool:
    try:
        ipaddress.ip_address(text.strip("[]"))
    except ValueError:
        return False
    return True
