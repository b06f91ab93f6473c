"""A rotary table driven by GRBL 1.1 over a serial link (1 unit = 1 degree on the table's axis).

URLs (query parameters are the constructor's options, all optional)::

    grbl:///dev/ttyUSB0?baud=115200&axis=X&feed=3600&timeout=3&poll=0.1&margin=2&home=1
    grbl://?port=socket://10.0.0.5:23&axis=Y      any pyserial URL through ``port=``
    socket://10.0.0.5:23?feed=1800                pyserial's socket:// and rfc2217:// directly

``feed`` degrees/min (capped by $110), ``timeout`` seconds for an answer or the banner, ``poll``
seconds between ``?`` while a move runs, ``margin`` seconds added to a move's computed duration,
``link_timeout`` seconds without a status report during a move before the link counts as lost
(0.8; GRBL answers ``?`` within milliseconds even mid-move); ``steps_per_degree`` (if given)
is written to $100 when it differs. ``home``: with homing enabled ($22=1) GRBL starts
alarm-locked; ``home=1`` (default) runs the homing cycle at connect, ``home=0`` unlocks with
``$X`` instead and warns that the angle is unreferenced.

Protocol (docs/GRBL.md; the serial link itself is `drivers.grbl_link`): a move is
``G90|G91 G1 X… F…`` followed by ``G4 P0``, whose ``ok`` comes only when the motion is complete;
``?`` is polled meanwhile to follow holds and alarms. Whether a move completed is decided by the
driver's own record of stops and resets, never by the order of the lines: GRBL may send the
``G4 P0``'s ``ok`` before the ``ALARM:3`` of a reset. `stop` is a feed hold (``!``), then, once
``Hold:0``, a reset that keeps the position; `emergency_stop` resets at once. Moves leave GRBL
in the distance mode they used (``move_by`` G91): lines of your own should set theirs.

About 480 lines: the turntable's URL, connect sequence, homing, two stops and moves, each short;
the serial link (send, answers, resync, reader, status polling) is `drivers.grbl_link`.
"""

from __future__ import annotations

import logging
import threading
import time
import urllib.parse

from .base import Turntable
from .errors import (
    DeviceError,
    DeviceNotFound,
    DeviceTimeout,
    FirmwareAlarm,
    FirmwareError,
    InvalidDeviceURL,
    MoveAborted,
)
from .grbl_link import GrblLink
from .grbl_protocol import (
    CYCLE_START,
    FEED_HOLD,
    StatusReport,
    alarm_error,
    alarm_meaning,
    format_number,
    homing_duration,
    move_duration,
    parse_options,
    parse_setting,
)

log = logging.getLogger(__name__)

_MAX_MOVE_TIMEOUT = 3600.0  # s
_POSITION_LOST = frozenset({1, 3})  # alarms GRBL documents as "position is likely lost"
_FLAG = {"1": True, "true": True, "yes": True, "0": False, "false": False, "no": False}
_QUERY = {
    "baud": ("baudrate", int),
    "axis": ("axis", str),
    "feed": ("feed", float),
    "timeout": ("timeout", float),
    "poll": ("poll_interval", float),
    "margin": ("margin", float),
    "link_timeout": ("link_timeout", float),
    "steps_per_degree": ("steps_per_degree", float),
    "home": ("home_at_connect", lambda v: _FLAG[v.lower()]),
    "port": ("port", str),
}


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
        home_at_connect: bool = True,
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
        self.home_at_connect = bool(home_at_connect)
        self.settings: dict[int, float] = {}
        self.link = GrblLink(port, baudrate, timeout)
        self._op_lock = threading.RLock()  # one line-based operation at a time
        self._stops = 0  # stop() / emergency_stop() calls so far: a move compares before/after
        self._homed = threading.Event()  # clear while a $H runs (GRBL sends no reports then)
        self._homed.set()
        self._homing_deadline = 0.0
        self._referenced = True

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
                except (ValueError, KeyError) as exc:
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

    @property
    def referenced(self) -> bool:
        """False after an emergency stop or an alarm that lost steps, or when a homing lock was
        unlocked without homing (``home=0``), until `home` runs."""
        return self._referenced

    def home(self) -> None:
        """Run the homing cycle ``$H`` if homing is enabled ($22=1), then make the current angle
        zero (G10 L20). Homing alarms raise `HomingFailed` saying what to check."""
        with self._op_lock:
            self._prepare_motion(allow_alarm=bool(self.settings.get(22)))
            if self.settings.get(22):
                self._run_homing_cycle()
            self.link.command(f"G10 L20 P0 {self.axis}0")
            self._referenced = True

    def move_to(self, degrees: float) -> None:
        self._move("G90", degrees)

    def move_by(self, degrees: float) -> None:
        self._move("G91", degrees)

    def wait_until_still(self, timeout: float | None = None) -> None:
        """Poll ``?`` until the axes are still (Idle, Hold:0, Alarm) and no line is pending."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            status = self.status(max(deadline - time.monotonic(), 0.05))
            if not status.moving and not (status.state == "Idle" and self.link.busy()):
                return
            if time.monotonic() >= deadline:
                raise DeviceTimeout(f"{self.port}: table still moving ({status.state}) at timeout")
            time.sleep(min(self.poll_interval, 0.02))

    def stop(self) -> None:
        """Controlled stop: feed hold ``!``, wait for ``Hold:0`` (decelerating at $120), then a
        soft reset, which GRBL does without an alarm once the hold is complete: the position
        stays valid and the next move needs no unlock. A move waiting in another thread raises
        `MoveAborted`. During a homing cycle (no hold possible) this is an emergency stop."""
        if not self._homed.is_set():
            self.emergency_stop()
            return
        self._count_stop()
        try:
            status = self.status()
            if status.moving or status.state == "Hold":
                self.link.write(FEED_HOLD)
                speed = (status.feed or self.max_rate) / 60.0
                deadline = time.monotonic() + speed / self.acceleration * 1.5 + self.timeout
                while (status := self.status()).moving:
                    if time.monotonic() >= deadline:
                        raise DeviceTimeout(f"{self.port}: the feed hold did not complete "
                                            f"({status.state}) within {self.timeout:g} s")
                    time.sleep(0.005)
        finally:  # a hold that failed still ends in the reset: a stop never leaves it moving
            self._reset_after_stop("stop")

    def emergency_stop(self) -> None:
        """Soft reset (0x18) at once: no deceleration. If the table was moving GRBL raises
        ALARM:3 ("position is likely lost") and the angle is unreferenced until `home`; the
        next move unlocks with ``$X`` and warns. A waiting move raises `MoveAborted`."""
        self._count_stop()
        self._reset_after_stop("emergency stop")

    # ------------------------------------------------------------------ GRBL extras
    def status(self, timeout: float | None = None) -> StatusReport:
        """A fresh status report (real-time ``?``, asked again if a report is lost). While a
        homing cycle runs GRBL reports nothing: this waits for the cycle to end first."""
        self.link.check_connected()
        if not self._homed.is_set():
            log.debug("%s: waiting for the homing cycle to end", self.port)
            self._homed.wait(max(self._homing_deadline - time.monotonic(), 0.0))
        return self.link.status(timeout)

    def feed_hold(self) -> None:
        """Real-time ``!``: decelerate to a stop (Hold:1, then Hold:0)."""
        self.link.check_connected()
        self.link.write(FEED_HOLD)

    def resume(self, timeout: float | None = None) -> None:
        """Real-time ``~`` once the hold is complete (GRBL ignores it during Hold:1)."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while (status := self.status()).state == "Hold" and status.substate != 0:
            if time.monotonic() >= deadline:
                raise DeviceTimeout(f"{self.port}: feed hold did not complete within timeout")
            time.sleep(0.005)
        self.link.write(CYCLE_START)

    def unlock(self) -> None:
        """Clear an alarm: a reset first if GRBL demands one, then ``$X``. The angle stays
        unreferenced if the alarm lost it (`home` references it)."""
        with self._op_lock:
            if self.link.critical:
                self.emergency_stop()
            self.command("$X")
            with self.link.cond:
                self.link.alarm = None

    def command(self, line: str, timeout: float | None = None) -> list[str]:
        """Send one line; return the lines printed before its ``ok`` (``$$``, ``$I``…)."""
        with self._op_lock:
            self.link.check_connected()
            if self.link.needs_resync:
                self.link.resync()
            return self.link.command(line, timeout)

    def send_gcode(self, lines, timeout: float | None = None) -> None:
        """Stream lines as fast as GRBL's RX buffer allows; raise the first `FirmwareError` after
        all are answered. ``timeout``: longest wait without any answer."""
        with self._op_lock:
            self.link.check_connected()
            if self.link.needs_resync:
                self.link.resync()
            pending = [self.link.send_line(line, timeout=timeout) for line in lines]
            errors = []
            for p in pending:
                try:
                    self.link.wait_ack(p, timeout or self.timeout)
                except FirmwareError as exc:
                    errors.append(exc)
            if errors:
                raise errors[0]

    def reconnect(self) -> None:
        """Reopen the port and run the connect sequence again (re-reads settings and angle)."""
        with self._op_lock:
            self.link.close()
            self._open_link()

    @property
    def version(self) -> str | None:
        return self.link.version

    @property
    def peak_outstanding(self) -> int:
        """Most bytes ever awaiting an answer (at most GRBL's RX buffer - 1)."""
        return self.link.peak_outstanding

    @property
    def max_rate(self) -> float:
        """$110 (or $111/$112 for Y/Z): the axis's top speed, degrees/min."""
        return self.settings[110 + "XYZ".index(self.axis)]

    @property
    def acceleration(self) -> float:
        """$120 (or $121/$122): degrees/s²."""
        return self.settings[120 + "XYZ".index(self.axis)]

    @property
    def homing_timeout(self) -> float:
        """Seconds a ``$H`` may take: the longest cycle the settings allow (every axis's
        search, see `homing_duration`) x 1.25, plus ``margin`` and ``timeout``."""
        try:
            return homing_duration(self.settings) * 1.25 + self.margin + self.timeout
        except KeyError:  # a firmware that does not list every homing setting: wait long
            return _MAX_MOVE_TIMEOUT

    # ------------------------------------------------------------------ life cycle
    def _open(self) -> None:
        self._open_link()

    def _open_link(self) -> None:
        self.link = GrblLink(self.port, self.baudrate, self.timeout)
        self.link.open()
        try:
            self._connect()
        except BaseException:
            self.link.close()
            raise

    def _close(self) -> None:
        self.link.close()

    def _connect(self) -> None:
        """Soft reset, banner, settings ($$), build info ($I); then the homing lock: home, or
        unlock with a warning (``home=0``) or after a previous session's alarm; the angle."""
        link = self.link
        try:
            link.soft_reset()
        except DeviceTimeout as exc:
            raise DeviceNotFound(
                f"no GRBL banner from {self.port} within {self.timeout:g} s"
            ) from exc
        locked = link.status().state == "Alarm"
        settings = dict(parse_setting(line) for line in link.command("$$") if line[:1] == "$")
        for line in link.command("$I"):
            options = parse_options(line)
            if options:
                link.rx_limit = options[2] - 1
        i = "XYZ".index(self.axis)
        missing = [f"${n}" for n in (100 + i, 110 + i, 120 + i) if n not in settings]
        if missing:
            raise DeviceError(f"{self.port}: '$$' did not list {', '.join(missing)}")
        if settings.get(13):
            raise DeviceError(f"{self.port}: GRBL reports positions in inches ($13=1); set $13=0 "
                              "so that 1 unit = 1 degree")
        self.settings = settings
        homing = bool(settings.get(22))
        self._referenced = True
        if locked and homing and self.home_at_connect:
            log.info("%s: homing enabled ($22=1): running the homing cycle ($H, up to %.0f s)",
                     self.port, self.homing_timeout)
            self._run_homing_cycle()
        elif locked:
            self._referenced = False
            if homing:
                log.warning("%s: homing enabled ($22=1) but home=0: unlocking with $X, the angle "
                            "is unreferenced until home()", self.port)
            else:
                log.warning("%s: GRBL was in an alarm from before; unlocking with $X, the angle "
                            "may be off until home()", self.port)
            link.command("$X")
        with link.cond:
            link.alarm = None
        link.command("G21")  # units of 1 (not 25.4): a startup block ($N) may have set G20
        if self.steps_per_degree and abs(settings[100 + i] - self.steps_per_degree) > 1e-6:
            log.info("%s: setting $%d=%s", self.port, 100 + i, self.steps_per_degree)
            link.command(f"${100 + i}={format_number(self.steps_per_degree)}")
            settings[100 + i] = float(format_number(self.steps_per_degree))
        log.info(
            "%s: Grbl %s, %s axis at %.3f deg, %.0f deg/min, %.0f deg/s^2, %.3f steps/deg",
            self.port, self.version, self.axis, self.angle, self.max_rate, self.acceleration,
            settings[100 + i],
        )  # fmt: skip

    def _run_homing_cycle(self) -> None:
        """``$H``; `status` and `angle` wait for it (GRBL sends no reports during the cycle)."""
        timeout = self.homing_timeout
        self._homing_deadline = time.monotonic() + timeout
        self._homed.clear()
        with self.link.cond:
            alarms = self.link.alarm_seq
        try:
            self.link.command("$H", timeout)
            with self.link.cond:  # real GRBL answers a failed cycle's $H with ok after its
                failed = self.link.alarm_seq > alarms  # ALARM:6-9 (then resets)
            if failed:
                raise FirmwareAlarm(self.link.last_alarm or 9, "$H")
        except FirmwareAlarm as exc:
            self._referenced = False
            raise alarm_error(exc.code, "$H") from None
        except DeviceTimeout as exc:
            self._referenced = False
            raise DeviceTimeout(f"{self.port}: the homing cycle did not end within {timeout:.0f} s "
                                f"(the longest the $ settings allow)") from exc
        finally:
            self._homed.set()
        with self.link.cond:
            self.link.alarm = None
        self._referenced = True

    # ------------------------------------------------------------------ stops
    def _count_stop(self) -> None:
        self.link.check_connected()
        with self.link.cond:
            self._stops += 1

    def _reset_after_stop(self, what: str) -> None:
        self.link.soft_reset()
        if self.status().state == "Alarm":  # our reset hit a motion: ALARM:3 or 6
            self._referenced = False
            log.warning("%s: %s while moving: GRBL reports the position as likely lost; the "
                        "angle is unreferenced until home()", self.port, what)

    # ------------------------------------------------------------------ motion
    def _move(self, mode: str, degrees: float) -> None:
        degrees = float(degrees)
        if degrees != degrees or abs(degrees) == float("inf"):
            raise ValueError(f"angle must be finite, got {degrees}")
        with self._op_lock:
            with self.link.cond:
                stops, resets = self._stops, self.link.reset_seq
            start = self._work_angle(self._prepare_motion())
            distance = abs(degrees - start) if mode == "G90" else abs(degrees)
            rate = min(self.feed, self.max_rate)
            # G21 on the line: a reset or $H runs the startup blocks ($N), which may set G20
            line = f"G21 {mode} G1 {self.axis}{format_number(degrees)} F{format_number(rate)}"
            duration = move_duration(distance, rate, self.acceleration)
            timeout = min(duration * 1.25 + self.margin, _MAX_MOVE_TIMEOUT)
            log.debug("%s: %s (%.2f s expected)", self.port, line, duration)
            try:
                move = self.link.send_line(line)
                done = self.link.send_line("G4 P0")
                self.link.wait_ack(move, self.timeout)
                self.link.wait_motion(done, timeout, line, self.poll_interval, self.link_timeout)
            except (FirmwareError, DeviceTimeout) as exc:
                if isinstance(exc, FirmwareAlarm) and exc.code in _POSITION_LOST:
                    self._referenced = False
                self._raise_if_aborted(stops, resets, line, degrees, exc)
                raise
            self._raise_if_aborted(stops, resets, line, degrees, None)

    def _raise_if_aborted(self, stops: int, resets: int, line: str, target: float, cause) -> None:
        """A stop or a reset since the move began means it did not complete, whatever the
        lines said (the ``ok`` of ``G4 P0`` may come before ALARM:3)."""
        with self.link.cond:
            stopped, reset = self._stops != stops, self.link.reset_seq != resets
        if isinstance(cause, FirmwareAlarm) and cause.code not in (3, 6) and not stopped:
            return  # an alarm of its own (limit switch, probe): the caller sees it as is
        if stopped or reset:
            why = "stopped" if stopped else "cut short by a firmware reset"
            raise MoveAborted(f"{self.port}: {line!r} was {why} before reaching "
                              f"{target:g} deg", target) from cause

    def _prepare_motion(self, allow_alarm: bool = False) -> StatusReport:
        """Check the link, resynchronise if needed, unlock after our own stop; the status."""
        link = self.link
        link.check_connected()
        if link.critical:
            code = link.alarm or link.last_alarm or 1
            raise FirmwareAlarm(code, alarm_meaning(code) + "; call unlock()")
        if link.needs_resync:
            link.resync()
        status = self.status()
        if status.state == "Run":  # lines `send_gcode` queued (their ok came when planned):
            done = link.send_line("G4 P0")  # the move starts where they end
            link.wait_motion(done, _MAX_MOVE_TIMEOUT, "G4 P0 (queued motion)",
                             self.poll_interval, self.link_timeout)
            status = self.status()
        if status.state == "Alarm" and not allow_alarm:
            if link.alarm is not None:
                raise FirmwareAlarm(link.alarm, alarm_meaning(link.alarm) + "; call unlock()")
            if self._referenced:
                log.info("%s: unlocking after reset ($X)", self.port)
            else:
                log.warning("%s: unlocking ($X) with an unreferenced angle: home() to reference "
                            "it", self.port)
            link.command("$X")
        return status

    def _work_angle(self, status: StatusReport) -> float:
        position = status.work_position(self.link.wco)
        for _ in range(31):  # GRBL prints WCO at least every 30 reports
            if position is not None:
                break
            status = self.status()
            position = status.work_position(self.link.wco)
        else:
            raise DeviceError(f"{self.port}: status reports give neither WPos nor WCO")
        return float(position["XYZ".index(self.axis)])
