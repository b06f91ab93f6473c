"""``sim://turntable``: the production GRBL driver talking to a simulated GRBL 1.1h.

    sim://turntable?station=default&instant=1&transport=url
    sim://turntable?instant=0&max_rate=36000&accel=7200&transport=pty&unplug_after_moves=3
    sim://turntable?homing=1&instant=0&time_scale=100&power_on_angle=90&home=0

``transport=url`` (default) reaches an in-process firmware through pyserial's ``simgrbl://``
handler; ``transport=pty`` serves it on a pseudo-terminal that the driver opens like a USB adapter.
Firmware parameters: see `sim.grbl_options.URL_OPTIONS` (``instant``, ``time_scale``,
``max_rate``, ``accel``, ``steps``, ``homing``, ``homing_cycles``, ``switches``,
``power_on_angle``, ``reset_ok_rate`` and the fault knobs); the driver's own (``feed``,
``timeout``, ``poll``, ``margin``, ``axis``, ``home``…) pass through to
`drivers.grbl.GrblTurntable`. The firmware is the station's
angle source, so a simulated camera on the same station renders the table's true angle.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import urllib.parse

from drivers.errors import InvalidDeviceURL
from drivers.grbl import GrblTurntable
from sim.grbl_firmware import GrblFirmware
from sim.grbl_options import firmware_options, station_firmware
from sim.serial_ports import URL_SCHEME, PtyTransport
from sim.station import get_station

_TRANSPORTS = ("url", "pty")


class SimTurntable(GrblTurntable):
    """A `GrblTurntable` whose serial port leads to the simulated firmware of ``station``."""

    schemes = ("sim",)

    def __init__(
        self,
        *,
        station: str = "default",
        transport: str = "url",
        firmware_options: dict | None = None,
        url: str = "",
        **driver_options,
    ):
        if transport not in _TRANSPORTS:
            raise InvalidDeviceURL(f"transport must be one of {_TRANSPORTS}, got {transport!r}")
        super().__init__(
            f"{URL_SCHEME}://{station}", url=url or "sim://turntable", **driver_options
        )
        self.station = station
        self.transport_kind = transport
        self.firmware_options = dict(firmware_options or {})
        self.firmware: GrblFirmware | None = None
        self.transport: PtyTransport | None = None
        self._tmpdir: str | None = None

    @classmethod
    def from_url(cls, url: str, **options) -> SimTurntable:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme != "sim" or parts.netloc not in ("turntable", ""):
            raise InvalidDeviceURL(f"not a simulated turntable URL: {url!r}")
        query = urllib.parse.parse_qs(parts.query, keep_blank_values=True)
        station = query.pop("station", ["default"])[-1]
        transport = query.pop("transport", ["url"])[-1]
        try:
            firmware = firmware_options(query)
        except ValueError as exc:
            raise InvalidDeviceURL(f"{exc} in {url!r}") from exc
        driver = cls.options_from_query(query)
        if "port" in driver or query:
            unknown = sorted(query) + (["port"] if "port" in driver else [])
            raise InvalidDeviceURL(f"unknown parameter(s) {', '.join(unknown)} in {url!r}")
        return cls(
            station=station,
            transport=transport,
            firmware_options=firmware,
            url=url,
            **{**driver, **options},
        )

    @classmethod
    def discover(cls) -> list[str]:
        return ["sim://turntable"]

    def _open(self) -> None:
        self.firmware = station_firmware(self.station, **self.firmware_options)
        get_station(self.station).angle_axis = self.axis  # the camera sees the axis we turn
        if self.transport_kind == "pty":
            self._tmpdir = tempfile.mkdtemp(prefix="scanstation-grbl-")
            link = os.path.join(self._tmpdir, "ttyGRBL")
            self.transport = PtyTransport(self.firmware, link=link).open()
            self.port = self.transport.port_name
        else:
            self.firmware.plug()
        try:
            super()._open()
        except BaseException:
            self._close_transport()
            raise

    def _close(self) -> None:
        try:
            super()._close()
        finally:
            self._close_transport()

    def reconnect(self) -> None:
        """Plug the cable back in (if it was pulled), then reconnect like the real driver."""
        if self.transport is not None and not self.firmware.plugged:
            self.transport.replug()
        elif self.firmware is not None:
            self.firmware.plug()
        super().reconnect()

    def _close_transport(self) -> None:
        if self.transport is not None:
            self.transport.close()
            self.transport = None
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None
