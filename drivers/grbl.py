"""A rotary table driven by GRBL 1.1 over a serial link (1 unit = 1 degree on the table's axis).

URLs (query parameters are the constructor's options, all optional)::

    grbl:///dev/ttyUSB0?baud=115200&axis=X&feed=3600&timeout=3&poll=0.1&margin=2
    grbl://?port=socket://10.0.0.5:23&axis=Y      any pyserial URL through ``port=``
    socket://10.0.0.5:23?feed=1800                pyserial's socket:// and rfc2217:// directly

``feed`` degrees/min (capped by $110), ``timeout`` seconds for an answer or the banner, ``poll``
seconds between ``?`` while a move runs, ``margin`` seconds added to a move's computed duration,
``link_timeout`` seconds without a status report during a move before the link counts as lost
(0.8; GRBL answers ``?`` within milliseconds even mid-move); ``steps_per_degree`` (if given)
is written to $100 when it differs.

Protocol (see /work/shared/GRBL.md): a background thread reads lines; each line sent is answered in
order by ``ok``/``error:N`` and the bytes of lines not yet answered never exceed GRBL's RX buffer
(character counting). A move is ``G90|G91 G1 X… F…`` followed by ``G4 P0``, whose ``ok`` comes only
when the motion is complete; ``?`` is polled meanwhile to follow holds and alarms. Moves leave
GRBL in the distance mode they used (``move_by`` G91): lines of your own should set theirs.
A lost answer is detected by timeout; the next operation resynchronises with ``$G``.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
import urllib.parse

import serial

from .base import Turntable
from .errors import (
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceTimeout,
    FirmwareAlarm,
    FirmwareError,
    InvalidDeviceURL,
)
from .grbl_protocol import (
    CYCLE_START,
    FEED_HOLD,
    RX_BUFFER_SIZE,
    SOFT_RESET,
    STATUS_QUERY,
    Kind,
    StatusReport,
    alarm_meaning,
    banner_version,
    clean_line,
    error_meaning,
    format_number,
    move_duration,
    parse_options,
    parse_response,
    parse_setting,
)

log = logging.getLogger(__name__)

_READ_TIMEOUT = 0.05  # s: reader wake-up period, bounds how late a pulled cable is noticed
_QUIET = 0.05  # s of silence that ends the stale-output drain at connect
_MAX_MOVE_TIMEOUT = 3600.0  # s
_QUERY = {
    "baud": ("baudrate", int),
    "axis": ("axis", str),
    "feed": ("feed", float),
    "timeout": ("timeout", float),
    "poll": ("poll_interval", float),
    "margin": ("margin", float),
    "link_timeout": ("link_timeout", float),
    "steps_per_degree": ("steps_per_degree", float),
    "port": ("port", str),
}


class _Pending:
    """A line sent and not yet answered."""

    def __init__(self, line: str, size: int, alarm_seq: int, sync: bool = False):
        self.line, self.size, self.alarm_seq, self.sync = line, size, alarm_seq, sync
        self.done = self.abandoned = False
        self.error: Exception | None = None
        self.info: list[str] = []


class GrblTurntable(Turntable):
    """GRBL turntable on ``port`` (a device path or any pyserial URL)."""

    schemes = ("grbl", "socket", "rfc2217")

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115200,
        axis: str = "X",
        feed: float = 3600.0,
        timeout: float = 3.0,
        poll_interval: float = 0.1,
        margin: float = 2.0,
        link_timeout: float = 0.8,
        steps_per_degree: float | None = None,
        url: str = "",
    ):
        super().__init__(url or f"grbl://{port}")
        axis = axis.upper()
        if axis not in ("X", "Y", "Z"):
            raise InvalidDeviceURL(f"axis must be X, Y or Z, got {axis!r}")
        if min(feed, timeout, poll_interval, link_timeout) <= 0 or margin < 0:
            raise InvalidDeviceURL("feed, timeout, poll and link_timeout must be > 0 and "
                                   "margin >= 0")
        self.port, self.baudrate, self.axis = port, int(baudrate), axis
        self.feed, self.timeout = feed, timeout
        self.poll_interval, self.margin = poll_interval, margin
        self.link_timeout = max(link_timeout, 2 * poll_interval)
        self.steps_per_degree = steps_per_degree
        self.settings: dict[int, float] = {}
        self.version: str | None = None
        self.peak_outstanding = 0  # most bytes ever awaiting an answer (<= RX buffer - 1)
        self._rx_limit = RX_BUFFER_SIZE - 1
        self._serial = None
        self._reader: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self._cond = threading.Condition()
        self._op_lock = threading.RLock()  # one line-based operation at a time
        self._send_lock = threading.Lock()  # keeps the answer queue in the order of the writes
        self._write_lock = threading.Lock()
        self._reset_link_state()

    # ------------------------------------------------------------------ construction, discovery
    @classmethod
    def from_url(cls, url: str, **options) -> GrblTurntable:
        parts = urllib.parse.urlsplit(url)
        query = urllib.parse.parse_qs(parts.query, keep_blank_values=True)
        parsed = cls.options_from_query(query)
        if parts.scheme == "grbl":
            port = parsed.pop("port", None) or parts.netloc + parts.path
            if query:
                raise InvalidDeviceURL(
                    f"unknown parameter(s) {', '.join(sorted(query))} in {url!r}"
                )
        elif parts.scheme in ("socket", "rfc2217"):
            if "port" in parsed:
                raise InvalidDeviceURL(f"port= is for grbl:// URLs only: {url!r}")
            rest = urllib.parse.urlencode(query, doseq=True)
            port = urllib.parse.urlunsplit((parts.scheme, parts.netloc, parts.path, rest, ""))
        else:
            raise InvalidDeviceURL(f"not a GRBL turntable URL: {url!r}")
        if not port:
            raise InvalidDeviceURL(f"no serial port in {url!r}")
        return cls(port, url=url, **{**parsed, **options})

    @staticmethod
    def options_from_query(query: dict[str, list[str]]) -> dict:
        """Pop this driver's parameters from a parsed query (``parse_qs``) as keyword arguments."""
        options = {}
        for key, (name, kind) in _QUERY.items():
            if key in query:
                raw = query.pop(key)[-1]
                try:
                    options[name] = kind(raw)
                except ValueError as exc:
                    raise InvalidDeviceURL(f"bad value {raw!r} for {key}=") from exc
        return options

    @classmethod
    def discover(cls) -> list[str]:
        from serial.tools import list_ports

        devices = sorted(p.device for p in list_ports.comports())
        return [f"grbl://{d}" for d in devices if d.startswith(("/dev/ttyUSB", "/dev/ttyACM"))]

    # ------------------------------------------------------------------ Turntable interface
    @property
    def angle(self) -> float:
        """Work-coordinate angle in degrees (MPos - WCO, or WPos), read from a fresh report."""
        return self._work_angle(self.status())

    def home(self) -> None:
        """Run ``$H`` if homing is enabled ($22=1), then make the current angle zero (G10 L20)."""
        with self._op_lock:
            self._prepare_motion(allow_alarm=bool(self.settings.get(22)))
            if self.settings.get(22):
                travel = 1.5 * self.settings.get(130, 360.0)
                seek = move_duration(travel, self.settings[25], self.acceleration)
                self._command("$H", seek + self.margin + self.timeout)
                with self._cond:
                    self._alarm = None
            self._command(f"G10 L20 P0 {self.axis}0")

    def move_to(self, degrees: float) -> None:
        self._move("G90", degrees)

    def move_by(self, degrees: float) -> None:
        self._move("G91", degrees)

    def wait_until_still(self, timeout: float | None = None) -> None:
        """Poll ``?`` until the axes are still (Idle, Hold:0, Alarm) and no line is pending."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            status = self.status()
            with self._cond:
                busy = any(not p.abandoned for p in self._acks)
            if not status.moving and not (status.state == "Idle" and busy):
                return
            if time.monotonic() >= deadline:
                raise DeviceTimeout(f"{self.port}: table still moving ({status.state}) at timeout")
            time.sleep(min(self.poll_interval, 0.02))

    def stop(self) -> None:
        """Soft reset (0x18): motion stops at once. GRBL then locks with ALARM:3 if it was moving;
        the next move unlocks it. A move waiting in another thread raises `FirmwareAlarm`."""
        self._check_connected()
        self._soft_reset()
        self.status()  # re-read the position and the lock state

    # ------------------------------------------------------------------ GRBL extras
    def status(self, timeout: float | None = None) -> StatusReport:
        """A fresh status report (real-time ``?``)."""
        self._check_connected()
        with self._cond:
            seq = self._status_seq
        self._write(STATUS_QUERY)
        self._await(lambda: self._status_seq > seq, timeout or self.timeout, "status report")
        return self._status

    def feed_hold(self) -> None:
        """Real-time ``!``: decelerate to a stop (Hold:1, then Hold:0)."""
        self._check_connected()
        self._write(FEED_HOLD)

    def resume(self, timeout: float | None = None) -> None:
        """Real-time ``~`` once the hold is complete (GRBL ignores it during Hold:1)."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while (status := self.status()).state == "Hold" and status.substate != 0:
            if time.monotonic() >= deadline:
                raise DeviceTimeout(f"{self.port}: feed hold did not complete within timeout")
            time.sleep(0.005)
        self._write(CYCLE_START)

    def unlock(self) -> None:
        """Clear an alarm: a reset first if GRBL demands one, then ``$X``."""
        with self._op_lock:
            if self._critical:
                self.stop()
            self.command("$X")
            with self._cond:
                self._alarm = None

    def command(self, line: str, timeout: float | None = None) -> list[str]:
        """Send one line; return the lines printed before its ``ok`` (``$$``, ``$I``…)."""
        with self._op_lock:
            self._check_connected()
            if self._needs_resync:
                self._resync()
            return self._command(line, timeout)

    def send_gcode(self, lines, timeout: float | None = None) -> None:
        """Stream lines as fast as GRBL's RX buffer allows; raise the first `FirmwareError` after
        all are answered. ``timeout``: longest wait without any answer."""
        with self._op_lock:
            self._check_connected()
            if self._needs_resync:
                self._resync()
            pending = [self._send_line(line, timeout=timeout) for line in lines]
            errors = []
            for p in pending:
                try:
                    self._wait_ack(p, timeout or self.timeout)
                except FirmwareError as exc:
                    errors.append(exc)
            if errors:
                raise errors[0]

    def reconnect(self) -> None:
        """Reopen the port and run the connect sequence again (re-reads settings and angle)."""
        with self._op_lock:
            self._close_port()
            self._open_port()
            try:
                self._connect()
            except BaseException:
                self._close_port()
                raise

    # ------------------------------------------------------------------ life cycle
    def _open(self) -> None:
        self._open_port()
        try:
            self._connect()
        except BaseException:
            self._close_port()
            raise

    def _close(self) -> None:
        self._close_port()

    def _reset_link_state(self) -> None:
        self._acks: collections.deque[_Pending] = collections.deque()
        self._outstanding = 0
        self._info: list[str] = []
        self._status: StatusReport | None = None
        self._status_seq = self._reset_seq = self._alarm_seq = 0
        self._wco: tuple[float, ...] | None = None
        self._last_alarm: int | None = None  # code of the latest ALARM line
        self._alarm: int | None = None  # an alarm nobody has cleared yet (not caused by stop())
        self._critical = self._needs_resync = self._stopping = False
        self._failure: DeviceDisconnected | None = None

    def _open_port(self) -> None:
        self._reset_link_state()
        try:
            port = serial.serial_for_url(
                self.port, baudrate=self.baudrate, timeout=_READ_TIMEOUT, write_timeout=self.timeout
            )
        except ValueError as exc:
            raise InvalidDeviceURL(f"bad serial port {self.port!r}: {exc}") from exc
        except (serial.SerialException, OSError) as exc:
            raise DeviceNotFound(f"cannot open {self.port}: {exc}") from exc
        self._serial = port
        try:
            self._drain()
        except BaseException:
            self._close_port()
            raise
        self._stop_reader.clear()
        self._reader = threading.Thread(target=self._read_loop, name=f"grbl-reader {self.port}")
        self._reader.start()

    def _drain(self) -> None:
        """Discard whatever the firmware printed before we came (GRBL does not reset on open)."""
        deadline = time.monotonic() + 1.0
        try:
            self._serial.reset_input_buffer()
            self._serial.timeout = _QUIET
            while time.monotonic() < deadline and (junk := self._serial.read(4096)):
                log.debug("%s: discarded %d stale bytes", self.port, len(junk))
            self._serial.timeout = _READ_TIMEOUT
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnected(f"{self.port} failed while opening: {exc}") from exc

    def _soft_reset(self) -> None:
        """0x18 and wait for the banner; an ALARM:3 it causes is ours, not an alarm to report."""
        with self._cond:
            seq, self._stopping = self._reset_seq, True
        try:
            self._write(SOFT_RESET)
            self._await(lambda: self._reset_seq > seq, self.timeout, "banner after reset")
        finally:
            with self._cond:
                self._stopping = False

    def _connect(self) -> None:
        """Soft reset, banner, unlock, settings ($$), build info ($I), angle."""
        try:
            self._soft_reset()
        except DeviceTimeout as exc:
            raise DeviceNotFound(
                f"no GRBL banner from {self.port} within {self.timeout:g} s"
            ) from exc
        if self.status().state == "Alarm":
            log.info("%s: clearing the alarm lock ($X)", self.port)
            self._command("$X")
        with self._cond:
            self._alarm = None
        settings = dict(parse_setting(line) for line in self._command("$$") if line[:1] == "$")
        for line in self._command("$I"):
            options = parse_options(line)
            if options:
                self._rx_limit = options[2] - 1
        i = "XYZ".index(self.axis)
        missing = [f"${n}" for n in (100 + i, 110 + i, 120 + i) if n not in settings]
        if missing:
            raise DeviceError(f"{self.port}: '$$' did not list {', '.join(missing)}")
        if settings.get(13):
            raise DeviceError(f"{self.port}: GRBL reports positions in inches ($13=1); set $13=0 "
                              "so that 1 unit = 1 degree")
        self._command("G21")  # units of 1 (not 25.4): a startup block ($N) may have set G20
        if self.steps_per_degree and abs(settings[100 + i] - self.steps_per_degree) > 1e-6:
            log.info("%s: setting $%d=%s", self.port, 100 + i, self.steps_per_degree)
            self._command(f"${100 + i}={format_number(self.steps_per_degree)}")
            settings[100 + i] = float(format_number(self.steps_per_degree))
        self.settings = settings
        log.info(
            "%s: Grbl %s, %s axis at %.3f deg, %.0f deg/min, %.0f deg/s^2, %.3f steps/deg",
            self.port, self.version, self.axis, self.angle, self.max_rate, self.acceleration,
            settings[100 + i],
        )  # fmt: skip

    def _close_port(self) -> None:
        port, reader = self._serial, self._reader
        self._stop_reader.set()
        if port is not None and hasattr(port, "cancel_read"):
            try:
                port.cancel_read()
            except (serial.SerialException, OSError):
                pass
        if reader is not None:
            reader.join()
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError) as exc:
                log.debug("%s: error while closing: %s", self.port, exc)
        self._serial = self._reader = None
        with self._cond:
            if self._failure is None:
                self._failure = DeviceDisconnected(f"{self.port} was closed")
            self._cond.notify_all()

    @property
    def max_rate(self) -> float:
        """$110 (or $111/$112 for Y/Z): the axis's top speed, degrees/min."""
        return self.settings[110 + "XYZ".index(self.axis)]

    @property
    def acceleration(self) -> float:
        """$120 (or $121/$122): degrees/s²."""
        return self.settings[120 + "XYZ".index(self.axis)]

    # ------------------------------------------------------------------ motion
    def _move(self, mode: str, degrees: float) -> None:
        degrees = float(degrees)
        if degrees != degrees or abs(degrees) == float("inf"):
            raise ValueError(f"angle must be finite, got {degrees}")
        with self._op_lock:
            start = self._work_angle(self._prepare_motion())
            distance = abs(degrees - start) if mode == "G90" else abs(degrees)
            rate = min(self.feed, self.max_rate)
            line = f"{mode} G1 {self.axis}{format_number(degrees)} F{format_number(rate)}"
            duration = move_duration(distance, rate, self.acceleration)
            timeout = min(duration * 1.25 + self.margin, _MAX_MOVE_TIMEOUT)
            log.debug("%s: %s (%.2f s expected)", self.port, line, duration)
            move = self._send_line(line)
            done = self._send_line("G4 P0")
            self._wait_ack(move, self.timeout)
            self._wait_motion(done, timeout, line)

    def _prepare_motion(self, allow_alarm: bool = False) -> StatusReport:
        """Check the link, resynchronise if needed, unlock after our own `stop`; the status."""
        self._check_connected()
        if self._critical:
            code = self._alarm or self._last_alarm or 1
            raise FirmwareAlarm(code, alarm_meaning(code) + "; call unlock()")
        if self._needs_resync:
            self._resync()
        status = self.status()
        if status.state == "Alarm" and not allow_alarm:
            if self._alarm is not None:
                raise FirmwareAlarm(self._alarm, alarm_meaning(self._alarm) + "; call unlock()")
            log.info("%s: unlocking after reset ($X)", self.port)
            self._command("$X")
        return status

    def _wait_motion(self, pending: _Pending, timeout: float, line: str) -> None:
        """Wait for the ``ok`` of ``G4 P0``, polling ``?``; time spent in a hold does not count.

        GRBL answers ``?`` within milliseconds whatever it is doing, so ``link_timeout`` s
        without a status report means the link is gone even when the port itself stays open
        (a USB bridge still enumerated, a network bridge): `DeviceDisconnected`."""
        deadline = last = heard = time.monotonic()
        deadline += timeout
        next_poll = last + self.poll_interval
        with self._cond:
            heard_seq = self._status_seq
            while not pending.done:
                self._raise_if_failed()
                now = time.monotonic()
                if self._status_seq != heard_seq:
                    heard, heard_seq = now, self._status_seq
                elif now - heard > self.link_timeout:
                    self._abandon(pending)
                    self._failure = DeviceDisconnected(
                        f"{self.port}: no status report for {self.link_timeout:.1f} s during "
                        f"{line!r} (cable pulled or board without power?)")
                    self._cond.notify_all()
                    raise self._failure
                if self._alarm_seq > pending.alarm_seq:
                    self._abandon(pending)
                    raise FirmwareAlarm(self._last_alarm, alarm_meaning(self._last_alarm), line)
                if self._status is not None and self._status.state == "Hold":
                    deadline += now - last
                last = now
                if now >= deadline:
                    self._abandon(pending)
                    raise DeviceTimeout(
                        f"{self.port}: {line!r} not finished within {timeout:.1f} s"
                    )
                if now >= next_poll:
                    self._cond.release()
                    try:
                        self._write(STATUS_QUERY)
                    finally:
                        self._cond.acquire()
                    next_poll = now + self.poll_interval
                wake = min(deadline, next_poll, heard + self.link_timeout + 1e-3)
                self._cond.wait(max(wake - now, 0.0))
        if pending.error is not None:
            raise pending.error

    def _work_angle(self, status: StatusReport) -> float:
        position = status.work_position(self._wco)
        for _ in range(31):  # GRBL prints WCO at least every 30 reports
            if position is not None:
                break
            status = self.status()
            position = status.work_position(self._wco)
        else:
            raise DeviceError(f"{self.port}: status reports give neither WPos nor WCO")
        return float(position["XYZ".index(self.axis)])

    # ------------------------------------------------------------------ lines and answers
    def _command(self, line: str, timeout: float | None = None) -> list[str]:
        return self._wait_ack(self._send_line(line), timeout or self.timeout)

    def _send_line(self, line: str, sync: bool = False, timeout: float | None = None) -> _Pending:
        """Write one line once GRBL's RX buffer has room for it (character counting)."""
        data = line.encode("ascii") + b"\n"
        if len(data) > self._rx_limit:
            raise ValueError(f"line longer than GRBL's {self._rx_limit}-byte buffer: {line!r}")
        with self._send_lock:
            with self._cond:
                if not sync:  # a resync line goes out even if lost answers inflated the count
                    room = lambda: self._outstanding + len(data) <= self._rx_limit  # noqa: E731
                    self._await(room, timeout or self.timeout, "room in GRBL's RX buffer", True)
                pending = _Pending(line, len(data), self._alarm_seq, sync)
                self._acks.append(pending)
                self._outstanding += len(data)
                self.peak_outstanding = max(self.peak_outstanding, self._outstanding)
            log.debug("%s > %s", self.port, line)
            self._write(data)
        return pending

    def _wait_ack(self, pending: _Pending, timeout: float) -> list[str]:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not pending.done:
                self._raise_if_failed()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._abandon(pending)
                    raise DeviceTimeout(
                        f"{self.port}: no answer to {pending.line!r} in {timeout:g} s"
                    )
                self._cond.wait(remaining)
        if pending.error is not None:
            raise pending.error
        return pending.info

    def _abandon(self, pending: _Pending) -> None:
        """Forget a line whose answer we stop waiting for; the next operation resynchronises."""
        if not pending.done:
            pending.abandoned = True
            self._needs_resync = True

    def _resync(self) -> None:
        """After a lost answer: ``$G``; its ``[GC:…]`` marks where the answers line up again."""
        log.info("%s: resynchronising the answer queue ($G)", self.port)
        self._wait_ack(self._send_line("$G", sync=True), self.timeout)
        with self._cond:
            self._needs_resync = False

    def _await(self, predicate, timeout: float, what: str, locked: bool = False) -> None:
        """Wait until ``predicate()`` (evaluated under the lock) or raise DeviceTimeout."""
        deadline = time.monotonic() + timeout
        if not locked:
            self._cond.acquire()
        try:
            while not predicate():
                self._raise_if_failed()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"{self.port}: no {what} within {timeout:g} s")
                self._cond.wait(remaining)
        finally:
            if not locked:
                self._cond.release()

    def _write(self, data: bytes) -> None:
        port = self._serial
        if port is None:
            raise DeviceError(f"{self.port} is not open")
        with self._cond:
            self._raise_if_failed()
        try:
            with self._write_lock:
                port.write(data)
        except serial.SerialTimeoutException as exc:
            raise DeviceTimeout(f"{self.port}: write timed out") from exc
        except (serial.SerialException, OSError) as exc:
            self._fail(exc)
            raise DeviceDisconnected(f"{self.port} disconnected: {exc}") from exc

    def _check_connected(self) -> None:
        if self._serial is None:
            raise DeviceError(f"{self.port} is not open")
        with self._cond:
            self._raise_if_failed()

    def _raise_if_failed(self) -> None:
        if self._failure is not None:
            raise DeviceDisconnected(str(self._failure)) from self._failure.__cause__

    def _fail(self, exc: BaseException) -> None:
        with self._cond:
            if self._failure is None:
                log.warning("%s disconnected: %s", self.port, exc)
                self._failure = DeviceDisconnected(f"{self.port} disconnected: {exc}")
                self._failure.__cause__ = exc
            self._cond.notify_all()

    # ------------------------------------------------------------------ reader thread
    def _read_loop(self) -> None:
        port, buffer = self._serial, bytearray()
        while not self._stop_reader.is_set():
            try:
                chunk = port.read(port.in_waiting or 1)
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                if not self._stop_reader.is_set():
                    self._fail(exc)
                return
            if not chunk:
                continue
            buffer += chunk
            *lines, rest = buffer.split(b"\n")
            buffer = bytearray(rest)
            for raw in lines:
                self._handle(clean_line(raw))
            if len(buffer) > 1024:
                log.warning("%s: dropping %d bytes without a line end", self.port, len(buffer))
                buffer.clear()

    def _handle(self, text: str) -> None:
        """Dispatch one received line (reader thread)."""
        response = parse_response(text)
        kind = response.kind
        with self._cond:
            if kind in (Kind.OK, Kind.ERROR):
                log.debug("%s < %s", self.port, text)
                if not self._acks:
                    log.warning("%s: unexpected %r (no line awaiting an answer)", self.port, text)
                    return
                pending = self._acks.popleft()
                self._outstanding -= pending.size
                pending.info, self._info = self._info, []
                if kind is Kind.ERROR:
                    meaning = error_meaning(response.code)
                    pending.error = FirmwareError(response.code, meaning, pending.line)
                pending.done = True
            elif kind is Kind.STATUS:
                self._status = response.status
                self._status_seq += 1
                if response.status.wco is not None:
                    self._wco = response.status.wco
            elif kind is Kind.ALARM:
                log.warning(
                    "%s: ALARM:%d %s", self.port, response.code, alarm_meaning(response.code)
                )
                self._last_alarm = response.code
                self._alarm_seq += 1
                if not (self._stopping and response.code in (3, 6)):
                    self._alarm = response.code
            elif kind is Kind.BANNER:
                self._on_reset(text)
            elif kind is Kind.MESSAGE:
                log.info("%s: %s", self.port, text)
                self._info.append(text)
                self._critical = self._critical or text == "[MSG:Reset to continue]"
            elif kind in (Kind.FEEDBACK, Kind.SETTING, Kind.STARTUP):
                self._info.append(text)
                if text.startswith("[GC:"):
                    self._drop_lost_answers()
            elif kind is Kind.UNKNOWN:
                log.warning("%s: ignoring unexpected line %r", self.port, text)
            self._cond.notify_all()

    def _on_reset(self, banner: str) -> None:
        """A banner: GRBL was reset, every line in flight is gone."""
        if not self._stopping and self._reset_seq > 0:
            log.warning("%s: firmware reset unexpectedly", self.port)
        self.version = banner_version(banner)
        self._reset_seq += 1
        self._critical = self._needs_resync = False
        for pending in self._acks:
            if self._alarm_seq > pending.alarm_seq:
                code = self._last_alarm
                pending.error = FirmwareAlarm(code, alarm_meaning(code), pending.line)
            else:
                pending.error = FirmwareError(
                    "reset", "firmware reset before answering", pending.line
                )
            pending.done = True
        self._acks.clear()
        self._outstanding, self._info = 0, []

    def _drop_lost_answers(self) -> None:
        """``[GC:…]`` of a resync ``$G``: lines queued before it lost their answers."""
        if not any(p.sync for p in self._acks):
            return
        while not self._acks[0].sync:
            lost = self._acks.popleft()
            self._outstanding -= lost.size
            lost.error = DeviceTimeout(f"{self.port}: the answer to {lost.line!r} was lost")
            lost.done = True
            log.warning("%s: no answer ever came to %r", self.port, lost.line)
