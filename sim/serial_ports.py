"""Transports that put a simulated GRBL (`sim.grbl_firmware`) behind a serial port.

- `PtyTransport`: a pseudo-terminal pair; the production driver opens ``grbl:///dev/pts/N`` (or
  a stable symlink) exactly as it opens a USB serial adapter. Closing the master end
  (`unplug`, or the firmware's ``unplug_after_moves`` fault) is a pulled cable.
- ``simgrbl://<station>?<firmware options>``: a pyserial URL handler for an in-process firmware
  (the station's, see `sim.grbl_options.station_firmware`), registered in
  ``serial.protocol_handler_packages`` when this module is imported. pyserial imports handlers as
  ``<package>.protocol_<scheme>``; the handler module is registered under that name here.
"""

from __future__ import annotations

import logging
import os
import select
import sys
import threading
import tty
import types
import urllib.parse

import serial

from sim.grbl_firmware import GrblFirmware
from sim.grbl_options import firmware_options, station_firmware

log = logging.getLogger(__name__)

URL_SCHEME = "simgrbl"
_IDLE_WAIT = 0.05  # s: the longest a pump or read sleeps without checking for a state change
_MAX_PENDING = 1 << 16  # bytes kept for a host that does not read; more is dropped, like a UART


class PtyTransport:
    """Serve ``firmware`` on a pseudo-terminal; ``port_name`` is what the driver opens.

    link : optional path of a symlink to the slave (stable across `replug`, like udev's
    /dev/serial/by-id names). Use as a context manager or call `open` and `close`.
    """

    def __init__(self, firmware: GrblFirmware, link: str | None = None):
        self.firmware = firmware
        self.link = link
        self._master = self._slave = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._slave_name = ""

    @property
    def port_name(self) -> str:
        return self.link or self._slave_name

    def open(self) -> PtyTransport:
        if self._thread is not None:
            return self
        self._master, self._slave = os.openpty()
        for fd in (self._master, self._slave):
            tty.setraw(fd)
        os.set_blocking(self._master, False)
        self._slave_name = os.ttyname(self._slave)
        if self.link:
            if os.path.lexists(self.link) and not os.path.islink(self.link):  # a user's file
                os.close(self._master)
                os.close(self._slave)
                self._master = self._slave = None
                raise FileExistsError(f"{self.link} exists and is not a symlink: the simulated "
                                      "port's link would replace it (name a free path)")
            tmp = f"{self.link}.{os.getpid()}.tmp"
            os.symlink(self._slave_name, tmp)
            os.replace(tmp, self.link)
        self.firmware.plug()
        self._stop.clear()
        self._thread = threading.Thread(target=self._pump, name=f"sim-grbl-pty {self._slave_name}")
        self._thread.start()
        return self

    def unplug(self) -> None:
        """Close the master end: the driver's next read fails as with a pulled USB cable."""
        self.firmware.unplug()
        self._join()

    def replug(self) -> None:
        """A new cable: a fresh pty (the symlink, if any, follows it)."""
        self.close(remove_link=False)
        self.open()

    def close(self, remove_link: bool = True) -> None:
        self._stop.set()
        self._join()
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None
        if remove_link and self.link and os.path.islink(self.link):
            os.unlink(self.link)

    def __enter__(self) -> PtyTransport:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def _join(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _pump(self) -> None:
        """Move bytes between the master end and the firmware until stopped or unplugged."""
        master, pending = self._master, bytearray()
        try:
            while not self._stop.is_set() and self.firmware.plugged:
                delay = self.firmware.next_event_delay()
                timeout = _IDLE_WAIT if delay is None else min(delay, _IDLE_WAIT)
                readable, _, _ = select.select([master], [], [], max(timeout, 0.0005))
                if readable:
                    try:
                        data = os.read(master, 4096)
                    except BlockingIOError:
                        data = b""
                    if data:
                        self.firmware.receive(data)
                pending += self.firmware.read_output()
                if pending:
                    try:
                        del pending[: os.write(master, pending)]
                    except BlockingIOError:  # nobody reads the slave: keep a little, drop more
                        del pending[:-_MAX_PENDING]
        except OSError as exc:
            log.warning("simulated GRBL pty pump stopped: %s", exc)
        finally:
            os.close(master)
            self._master = None


class SimGrblSerial(serial.SerialBase):
    """A pyserial port whose far end is an in-process `GrblFirmware` (``simgrbl://station``)."""

    def open(self) -> None:
        if self._port is None:
            raise serial.SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise serial.SerialException("Port is already open.")
        parts = urllib.parse.urlsplit(self._port)
        if parts.scheme != URL_SCHEME:
            raise serial.SerialException(f"expected a {URL_SCHEME}:// URL, got {self._port!r}")
        query = urllib.parse.parse_qs(parts.query, keep_blank_values=True)
        options = firmware_options(query)
        if query:
            raise ValueError(f"unknown parameter(s) {', '.join(sorted(query))} in {self._port!r}")
        self.firmware = station_firmware(parts.netloc or "default", **options)
        if not self.firmware.plugged:
            raise serial.SerialException(f"{self._port}: the cable is unplugged")
        self._buffer = bytearray()
        self._cancel = threading.Event()
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def _reconfigure_port(self) -> None:
        """Baud rate and framing mean nothing in process."""

    def _check(self) -> None:
        if not self.is_open:
            raise serial.PortNotOpenError()
        if not self.firmware.plugged:
            raise serial.SerialException(f"{self._port}: device disconnected (cable unplugged)")

    def _pull(self) -> None:
        self._buffer += self.firmware.read_output()

    @property
    def in_waiting(self) -> int:
        self._check()
        self._pull()
        return len(self._buffer)

    def read(self, size: int = 1) -> bytes:
        self._check()
        timeout = serial.Timeout(self._timeout)
        self._cancel.clear()
        while True:
            self._pull()
            if len(self._buffer) >= size or timeout.expired() or self._cancel.is_set():
                break
            left = timeout.time_left()
            self.firmware.wait(_IDLE_WAIT if left is None else min(left, _IDLE_WAIT))
            self._check()
        data = bytes(self._buffer[:size])
        del self._buffer[:size]
        return data

    def write(self, data: bytes) -> int:
        self._check()
        data = bytes(data)
        self.firmware.receive(data)
        return len(data)

    def cancel_read(self) -> None:
        self._cancel.set()

    def reset_input_buffer(self) -> None:
        self._check()
        self._pull()
        self._buffer.clear()

    def reset_output_buffer(self) -> None:
        self._check()


def register_url_handler() -> None:
    """Make ``serial.serial_for_url("simgrbl://…")`` reach `SimGrblSerial` (idempotent)."""
    handler = f"{__name__}.protocol_{URL_SCHEME}"
    if handler not in sys.modules:
        module = types.ModuleType(handler, "pyserial handler for simgrbl:// (sim.serial_ports)")
        module.Serial = SimGrblSerial
        sys.modules[handler] = module
    if __name__ not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(__name__)


register_url_handler()
