"""The serial link to a GRBL 1.1 board: port, reader thread, lines and their answers.

A background thread reads lines; each line sent is answered in order by ``ok``/``error:N`` and
the bytes of lines not yet answered never exceed GRBL's RX buffer (character counting). A lost
answer is detected by timeout; the next operation resynchronises with ``$G`` (`resync`), whose
``[GC:…]`` marks where the answers line up again. A banner means the firmware reset: every line
in flight fails. Real-time bytes (``?``, ``!``, ``~``, 0x18) go out at once (`write`). Knows
nothing of turntables (`drivers.grbl`). About 420 lines: one link object, a reader thread and
the waits on it, which share one lock and read best together.
"""

from __future__ import annotations

import collections
import logging
import threading
import time

import serial

from .errors import DeviceDisconnected, DeviceError, DeviceNotFound, DeviceTimeout, FirmwareError
from .grbl_protocol import (
    RX_BUFFER_SIZE,
    SOFT_RESET,
    STATUS_QUERY,
    Kind,
    StatusReport,
    alarm_error,
    alarm_meaning,
    banner_version,
    clean_line,
    error_meaning,
    parse_response,
)

log = logging.getLogger("drivers.grbl")

_READ_TIMEOUT = 0.05  # s: reader wake-up period, bounds how late a pulled cable is noticed
_QUIET = 0.05  # s of silence that ends the stale-output drain at connect
_STATUS_RETRY = 0.25  # s: a `?` unanswered this long (a garbled report) is sent again


class Pending:
    """A line sent and not yet answered."""

    def __init__(self, line: str, size: int, alarm_seq: int, sync: bool = False):
        self.line, self.size, self.alarm_seq, self.sync = line, size, alarm_seq, sync
        self.done = self.abandoned = False
        self.error: Exception | None = None
        self.info: list[str] = []


class GrblLink:
    """The link to the GRBL board on ``port`` (a device path or any pyserial URL).

    State shared with the reader thread is read and written under ``cond``."""

    def __init__(self, port: str, baudrate: int = 115200, timeout: float = 3.0):
        self.port, self.baudrate, self.timeout = port, int(baudrate), timeout
        self.version: str | None = None
        self.peak_outstanding = 0  # most bytes ever awaiting an answer (<= RX buffer - 1)
        self.rx_limit = RX_BUFFER_SIZE - 1
        self.cond = threading.Condition()
        self._serial = None
        self._reader: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self._send_lock = threading.Lock()  # keeps the answer queue in the order of the writes
        self._write_lock = threading.Lock()
        self.reset_state()

    def reset_state(self) -> None:
        self.acks: collections.deque[Pending] = collections.deque()
        self.outstanding = 0
        self._info: list[str] = []
        self.status_report: StatusReport | None = None
        self.status_seq = self.reset_seq = self.alarm_seq = 0
        self.wco: tuple[float, ...] | None = None
        self.last_alarm: int | None = None  # code of the latest ALARM line
        self.alarm: int | None = None  # an alarm nobody has cleared yet (not caused by a stop)
        self.critical = self.needs_resync = self.stopping = False
        self.failure: DeviceDisconnected | None = None

    # ------------------------------------------------------------------ open, close
    def open(self) -> None:
        self.reset_state()
        try:
            port = serial.serial_for_url(
                self.port, baudrate=self.baudrate, timeout=_READ_TIMEOUT, write_timeout=self.timeout
            )
        except ValueError as exc:
            from .errors import InvalidDeviceURL

            raise InvalidDeviceURL(f"bad serial port {self.port!r}: {exc}") from exc
        except (serial.SerialException, OSError) as exc:
            raise DeviceNotFound(f"cannot open {self.port}: {exc}") from exc
        self._serial = port
        try:
            self._drain()
        except BaseException:
            self.close()
            raise
        self._stop_reader.clear()
        self._reader = threading.Thread(target=self._read_loop, name=f"grbl-reader {self.port}",
                                        daemon=True)  # (a port left open must not hang an exit)
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

    def close(self) -> None:
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
        with self.cond:
            if self.failure is None:
                self.failure = DeviceDisconnected(f"{self.port} was closed")
            self.cond.notify_all()

    # ------------------------------------------------------------------ requests
    def status(self, timeout: float | None = None) -> StatusReport:
        """A fresh status report: ``?``, sent again every 0.25 s until one parses (a report
        garbled on the line is lost, not fatal) or ``timeout`` s have passed."""
        timeout = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        while True:
            self.check_connected()
            with self.cond:
                seq = self.status_seq
            self.write(STATUS_QUERY)
            remaining = deadline - time.monotonic()
            try:
                self.wait_for(lambda seq=seq: self.status_seq > seq, min(_STATUS_RETRY, remaining),
                              "status report")
                return self.status_report
            except DeviceTimeout:
                if time.monotonic() >= deadline:
                    raise DeviceTimeout(
                        f"{self.port}: no status report within {timeout:g} s") from None
                log.debug("%s: no status report yet, asking again", self.port)

    def soft_reset(self, timeout: float | None = None) -> None:
        """0x18 and wait for the banner; an ALARM:3/6 it causes is ours, not one to report."""
        with self.cond:
            seq, self.stopping = self.reset_seq, True
        try:
            self.write(SOFT_RESET)
            self.wait_for(lambda: self.reset_seq > seq, timeout or self.timeout,
                          "banner after reset")
        finally:
            with self.cond:
                self.stopping = False

    def command(self, line: str, timeout: float | None = None) -> list[str]:
        """Send one line, wait for its answer; the lines printed before its ``ok``."""
        return self.wait_ack(self.send_line(line), timeout or self.timeout)

    def send_line(self, line: str, sync: bool = False, timeout: float | None = None) -> Pending:
        """Write one line once GRBL's RX buffer has room for it (character counting)."""
        data = line.encode("ascii") + b"\n"
        if len(data) > self.rx_limit:
            raise ValueError(f"line longer than GRBL's {self.rx_limit}-byte buffer: {line!r}")
        with self._send_lock:
            with self.cond:
                if not sync:  # a resync line goes out even if lost answers inflated the count
                    room = lambda: self.outstanding + len(data) <= self.rx_limit  # noqa: E731
                    self.wait_for(room, timeout or self.timeout, "room in GRBL's RX buffer", True)
                pending = Pending(line, len(data), self.alarm_seq, sync)
                self.acks.append(pending)
                self.outstanding += len(data)
                self.peak_outstanding = max(self.peak_outstanding, self.outstanding)
            log.debug("%s > %s", self.port, line)
            self.write(data)
        return pending

    def wait_ack(self, pending: Pending, timeout: float) -> list[str]:
        deadline = time.monotonic() + timeout
        with self.cond:
            while not pending.done:
                self.raise_if_failed()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self.abandon(pending)
                    raise DeviceTimeout(
                        f"{self.port}: no answer to {pending.line!r} in {timeout:g} s"
                    )
                self.cond.wait(remaining)
        if pending.error is not None:
            raise pending.error
        return pending.info

    def wait_motion(self, pending: Pending, timeout: float, line: str, poll_interval: float,
                    link_timeout: float) -> None:
        """Wait for the ``ok`` of ``G4 P0``, polling ``?``; time spent in a hold does not count.

        GRBL answers ``?`` within milliseconds whatever it is doing, so ``link_timeout`` s
        without a status report means the link is gone even when the port itself stays open
        (a USB bridge still enumerated, a network bridge): `DeviceDisconnected`."""
        deadline = last = heard = time.monotonic()
        deadline += timeout
        next_poll = last + poll_interval
        with self.cond:
            heard_seq = self.status_seq
            while not pending.done:
                self.raise_if_failed()
                now = time.monotonic()
                if self.status_seq != heard_seq:
                    heard, heard_seq = now, self.status_seq
                elif now - heard > link_timeout:
                    self.abandon(pending)
                    raise self.fail(
                        TimeoutError(line),
                        f"{self.port}: no status report for {link_timeout:.1f} s during "
                        f"{line!r} (cable pulled or board without power?)")
                if self.alarm_seq > pending.alarm_seq:
                    self.abandon(pending)
                    raise alarm_error(self.last_alarm, line)
                if self.status_report is not None and self.status_report.state == "Hold":
                    deadline += now - last
                last = now
                if now >= deadline:
                    self.abandon(pending)
                    raise DeviceTimeout(
                        f"{self.port}: {line!r} not finished within {timeout:.1f} s"
                    )
                if now >= next_poll:
                    self.cond.release()
                    try:
                        self.write(STATUS_QUERY)
                    finally:
                        self.cond.acquire()
                    next_poll = now + poll_interval
                wake = min(deadline, next_poll, heard + link_timeout + 1e-3)
                self.cond.wait(max(wake - now, 0.0))
        if pending.error is not None:
            raise pending.error

    def abandon(self, pending: Pending) -> None:
        """Forget a line whose answer we stop waiting for; the next operation resynchronises."""
        if not pending.done:
            pending.abandoned = True
            self.needs_resync = True

    def busy(self) -> bool:
        """Lines still awaiting an answer (other than abandoned ones)."""
        with self.cond:
            return any(not p.abandoned for p in self.acks)

    def resync(self) -> None:
        """After a lost answer: ``$G``; its ``[GC:…]`` marks where the answers line up again."""
        log.info("%s: resynchronising the answer queue ($G)", self.port)
        self.wait_ack(self.send_line("$G", sync=True), self.timeout)
        with self.cond:
            self.needs_resync = False

    def wait_for(self, predicate, timeout: float, what: str, locked: bool = False) -> None:
        """Wait until ``predicate()`` (evaluated under the lock) or raise DeviceTimeout."""
        deadline = time.monotonic() + timeout
        if not locked:
            self.cond.acquire()
        try:
            while not predicate():
                self.raise_if_failed()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"{self.port}: no {what} within {timeout:g} s")
                self.cond.wait(remaining)
        finally:
            if not locked:
                self.cond.release()

    def write(self, data: bytes) -> None:
        port = self._serial
        if port is None:
            raise DeviceError(f"{self.port} is not open")
        with self.cond:
            self.raise_if_failed()
        try:
            with self._write_lock:
                port.write(data)
        except serial.SerialTimeoutException as exc:
            raise DeviceTimeout(f"{self.port}: write timed out") from exc
        except (serial.SerialException, OSError) as exc:
            self.fail(exc)
            raise DeviceDisconnected(f"{self.port} disconnected: {exc}") from exc

    def check_connected(self) -> None:
        if self._serial is None:
            raise DeviceError(f"{self.port} is not open")
        with self.cond:
            self.raise_if_failed()

    def raise_if_failed(self) -> None:
        if self.failure is not None:
            raise DeviceDisconnected(str(self.failure)) from self.failure.__cause__

    def fail(self, exc: BaseException, message: str | None = None) -> DeviceDisconnected:
        """Mark the link lost (first cause wins); the error to raise."""
        with self.cond:
            if self.failure is None:
                text = message or f"{self.port} disconnected: {exc}"
                log.warning("%s", text)
                self.failure = DeviceDisconnected(text)
                self.failure.__cause__ = exc
            self.cond.notify_all()
            return self.failure

    # ------------------------------------------------------------------ reader thread
    def _read_loop(self) -> None:
        port, buffer = self._serial, bytearray()
        while not self._stop_reader.is_set():
            try:
                chunk = port.read(port.in_waiting or 1)
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                if not self._stop_reader.is_set():
                    self.fail(exc)
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
        with self.cond:
            if kind in (Kind.OK, Kind.ERROR):
                log.debug("%s < %s", self.port, text)
                if not self.acks:
                    log.warning("%s: unexpected %r (no line awaiting an answer)", self.port, text)
                    return
                pending = self.acks.popleft()
                self.outstanding -= pending.size
                pending.info, self._info = self._info, []
                if kind is Kind.ERROR:
                    meaning = error_meaning(response.code)
                    pending.error = FirmwareError(response.code, meaning, pending.line)
                pending.done = True
            elif kind is Kind.STATUS:
                self.status_report = response.status
                self.status_seq += 1
                if response.status.wco is not None:
                    self.wco = response.status.wco
            elif kind is Kind.ALARM:
                log.warning(
                    "%s: ALARM:%d %s", self.port, response.code, alarm_meaning(response.code)
                )
                self.last_alarm = response.code
                self.alarm_seq += 1
                if not (self.stopping and response.code in (3, 6)):
                    self.alarm = response.code
            elif kind is Kind.BANNER:
                self._on_reset(text)
            elif kind is Kind.MESSAGE:
                log.info("%s: %s", self.port, text)
                self._info.append(text)
                self.critical = self.critical or text == "[MSG:Reset to continue]"
            elif kind in (Kind.FEEDBACK, Kind.SETTING, Kind.STARTUP):
                self._info.append(text)
                if text.startswith("[GC:"):
                    self._drop_lost_answers()
            elif kind is Kind.UNKNOWN:
                log.warning("%s: ignoring unexpected line %r", self.port, text)
            self.cond.notify_all()

    def _on_reset(self, banner: str) -> None:
        """A banner: GRBL was reset, every line in flight is gone."""
        if not self.stopping and self.reset_seq > 0:
            log.warning("%s: firmware reset unexpectedly", self.port)
        self.version = banner_version(banner)
        self.reset_seq += 1
        self.critical = self.needs_resync = False
        for pending in self.acks:
            if self.alarm_seq > pending.alarm_seq:
                pending.error = alarm_error(self.last_alarm, pending.line)
            else:
                pending.error = FirmwareError(
                    "reset", "firmware reset before answering", pending.line
                )
            pending.done = True
        self.acks.clear()
        self.outstanding, self._info = 0, []

    def _drop_lost_answers(self) -> None:
        """``[GC:…]`` of a resync ``$G``: lines queued before it lost their answers."""
        if not any(p.sync for p in self.acks):
            return
        while not self.acks[0].sync:
            lost = self.acks.popleft()
            self.outstanding -= lost.size
            lost.error = DeviceTimeout(f"{self.port}: the answer to {lost.line!r} was lost")
            lost.done = True
            log.warning("%s: no answer ever came to %r", self.port, lost.line)
