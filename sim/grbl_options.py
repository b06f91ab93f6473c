"""Simulated GRBL firmwares from URL query parameters, and the firmware of each simulated station.

``simgrbl://station?instant=0&homing=1`` (`sim.serial_ports`) and ``sim://turntable?...``
(`sim.turntable`) take the `GrblFirmware` constructor's arguments as query parameters
(`URL_OPTIONS`); repeatable ones take ``KEY:VALUE`` (``error_on=X90:33``).
"""

from __future__ import annotations

import inspect

from sim.grbl_firmware import GrblFirmware, _pairs
from sim.station import get_station

_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def _flag(text: str) -> bool:
    if text.lower() not in _TRUE + _FALSE:
        raise ValueError(f"expected a boolean, got {text!r}")
    return text.lower() in _TRUE


#: URL query parameter -> (constructor argument, parser). Repeatable ones take ``KEY:VALUE``.
URL_OPTIONS = {
    "instant": ("instant", _flag),
    "max_rate": ("max_rate", float),
    "accel": ("acceleration", float),
    "steps": ("steps_per_degree", float),
    "homing": ("homing", _flag),
    "homing_cycles": ("homing_cycles", str),
    "switches": ("switches", str),
    "time_scale": ("time_scale", float),
    "power_on_angle": ("power_on_angle", float),
    "reset_ok_rate": ("reset_ok_rate", float),
    "garble_status_every": ("garble_status_every", int),
    "unplug_after_moves": ("unplug_after_moves", int),
    "silent_after_moves": ("silent_after_moves", int),
    "garbage_every": ("garbage_every", int),
    "seed": ("random_state", int),
    "error_on": ("error_on", lambda v: _pairs(v, int)),
    "delay_on": ("delay_on", lambda v: _pairs(v, float)),
    "alarm_on": ("alarm_on", lambda v: _pairs(v, int)),
    "drop_on": ("drop_on", tuple),
}
_REPEATABLE = {"error_on", "delay_on", "alarm_on", "drop_on"}


def firmware_options(query: dict[str, list[str]]) -> dict:
    """Pop the firmware's parameters from a parsed URL query (``urllib.parse.parse_qs``) and
    return constructor arguments; ValueError names a bad value."""
    options = {}
    for key, (name, parse) in URL_OPTIONS.items():
        if key in query:
            raw = query.pop(key)
            try:
                options[name] = parse(raw if key in _REPEATABLE else raw[-1])
            except (ValueError, TypeError) as exc:
                raise ValueError(f"bad value {raw!r} for {key}=: {exc}") from exc
    return options


def _full_config(options: dict) -> dict:
    params = inspect.signature(GrblFirmware).parameters
    config = {k: p.default for k, p in params.items() if k != "clock"}
    config.update(options)
    return config


def station_firmware(station: str = "default", **options) -> GrblFirmware:
    """The firmware of a simulated station, created (and made the station's angle source) when
    the station has none or one with other options; options empty: reuse whatever is there."""
    current = get_station(station).angle_source
    if isinstance(current, GrblFirmware):
        if not options or _full_config(current.config) == _full_config(options):
            return current
    firmware = GrblFirmware(**options)
    get_station(station).angle_source = firmware
    return firmware
