"""A GRBL 1.1h firmware simulator: the serial protocol and a real-time trapezoidal motion model.

The firmware is passive and thread-safe: a transport (`sim.serial_ports`) hands it the bytes the
host wrote (`receive`) and collects what it prints (`read_output`). Motion is a function of the
clock (a rest-to-rest trapezoid per planner block), so the table's angle is exact at any instant
without a thread of its own (`position_degrees`). ``instant=True`` (default) completes every move
when it is planned, like ophyd's ``SimMotor(instant=True)``.

Simulated subset: G0 G1 G4 G10 L2/L20 G17 G20 G21 G53 G54-G59 G80 G90 G91 G92 G92.1 G94, M0-M9 M30
(accepted, no effect), F S T N; ``$ $$ $# $G $I $N $X $H $J= $n=v``; real-time ``? ! ~ 0x18 0x85``.
Other G/M codes answer ``error:20``; ``$C``/``$SLP``/``$RST`` answer ``error:3``. Each block is
planned from rest to rest (no junction blending). Fault knobs (constructor arguments, URL query
parameters through `firmware_options`) match lines by substring after GRBL's normalisation (upper
case, no spaces): ``error_on={"X90": 33}`` answers ``error:33`` to ``G1 X90 F600``.
"""

from __future__ import annotations

import collections
import dataclasses
import heapq
import inspect
import itertools
import logging
import math
import random
import re
import threading
import time

import numpy as np

from drivers.grbl_protocol import CRITICAL_ALARMS, LINE_MAX, PLANNER_BLOCKS, RX_BUFFER_SIZE
from sim.station import get_station

log = logging.getLogger(__name__)

VERSION, BUILD = "1.1h", "20190830"
BANNER = f"Grbl {VERSION} ['$' for help]"
LOCK_MESSAGE = "[MSG:'$H'|'$X' to unlock]"
HELP = "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"
RX_CAPACITY = RX_BUFFER_SIZE - 1  # a ring buffer keeps one slot free
GRBL_DEFAULTS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0, 20: 0, 21: 0,
    22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: 250.0, 101: 250.0, 102: 250.0, 110: 500.0, 111: 500.0, 112: 500.0,
    120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0,
}  # fmt: skip
_INT_SETTINGS = frozenset(n for n in GRBL_DEFAULTS if n < 100 and n not in (11, 12, 24, 25, 27))
_G_GROUPS = {0: 1, 1: 1, 80: 1, 4: 0, 10: 0, 53: 0, 92: 0, 92.1: 0, 17: 2, 90: 3, 91: 3, 94: 5}
_G_GROUPS.update({20: 6, 21: 6, **{code: 12 for code in range(54, 60)}})
_M_GROUPS = {0: 4, 1: 4, 2: 4, 30: 4, 3: 7, 4: 7, 5: 7, 7: 8, 8: 8, 9: 8}
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")
_DEFERRED, _RETRY = object(), object()  # answer later (sync, dwell, homing); planner full
_STATES_THAT_RUN_BLOCKS = ("Idle", "Run", "Jog", "Home")


class GcodeError(Exception):
    """A line GRBL refuses; ``code`` is the ``error:N`` number."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def normalize_line(raw: str) -> str:
    """What GRBL keeps of a line: no whitespace, control characters or comments; upper case."""
    kept, in_comment = [], False
    for ch in raw:
        if in_comment:
            in_comment = ch != ")"
        elif ch == "(":
            in_comment = True
        elif ch == ";":
            break
        elif " " < ch < "\x7f":
            kept.append(ch.upper())
    return "".join(kept)


def split_words(line: str) -> list[tuple[str, float]]:
    """``"G1X10F600"`` -> ``[("G", 1.0), ("X", 10.0), ("F", 600.0)]``; GcodeError 1 or 2."""
    words, i = [], 0
    while i < len(line):
        if not "A" <= line[i] <= "Z":
            raise GcodeError(1)
        match = _NUMBER.match(line, i + 1)
        if match is None:
            raise GcodeError(2)
        words.append((line[i], float(match.group())))
        i = match.end()
    return words


@dataclasses.dataclass(frozen=True)
class Profile:
    """Distance (units) along a straight move over time (s): from speed ``v0`` accelerate at
    ``accel`` to ``v_peak``, cruise ``t_cruise`` s, decelerate to rest."""

    v0: float
    v_peak: float
    accel: float
    t_cruise: float

    @classmethod
    def trapezoid(cls, distance: float, speed: float, accel: float) -> Profile:
        v = min(speed, math.sqrt(distance * accel))
        return cls(0.0, v, accel, max((distance - v * v / accel) / v, 0.0) if v > 0 else 0.0)

    @classmethod
    def stop(cls, v0: float, accel: float) -> Profile:
        return cls(v0, v0, accel, 0.0)

    @property
    def duration(self) -> float:
        return (2 * self.v_peak - self.v0) / self.accel + self.t_cruise

    def at(self, t: float) -> tuple[float, float]:
        """(distance, speed) ``t`` s after the start."""
        a, v0, vp = self.accel, self.v0, self.v_peak
        t_acc = (vp - v0) / a
        if t <= 0:
            return 0.0, v0
        if t < t_acc:
            return v0 * t + 0.5 * a * t * t, v0 + a * t
        s, t = (v0 + vp) / 2 * t_acc + vp * min(t - t_acc, self.t_cruise), t - t_acc - self.t_cruise
        if t <= 0:
            return s, vp
        t = min(t, vp / a)
        return s + vp * t - 0.5 * a * t * t, vp - a * t


@dataclasses.dataclass
class _Block:
    target: np.ndarray  # (3,) machine units
    rate: float  # requested units/min, limited per axis when the block starts
    kind: str  # "run", "jog" or "home"
    planned_at: float
    event: tuple | None = None  # ("unplug", None) or ("alarm", code), fired mid-move


@dataclasses.dataclass
class _Segment:
    origin: np.ndarray
    unit: np.ndarray
    profile: Profile
    t0: float
    kind: str  # block kind, "hold" (decelerating into a hold) or "cancel" (jog cancel)
    end: np.ndarray

    @property
    def end_time(self) -> float:
        return self.t0 + self.profile.duration

    def at(self, now: float) -> tuple[np.ndarray, float]:
        if now >= self.end_time:
            return self.end.copy(), 0.0
        s, v = self.profile.at(now - self.t0)
        return self.origin + self.unit * s, v


def _pairs(values, kind) -> dict:
    pairs = values.items() if isinstance(values, dict) else (v.rsplit(":", 1) for v in values)
    return {normalize_line(k): kind(v) for k, v in pairs if normalize_line(k)}


class GrblFirmware:
    """GRBL 1.1h on a simulated rotary table; 1 unit = 1 degree on every axis.

    max_rate : $110-$112, degrees/min.  acceleration : $120-$122, degrees/s².
    steps_per_degree : $100-$102.  homing : $22 (starts locked, ``$H`` returns to 0).
    """

    def __init__(
        self,
        *,
        instant: bool = True,
        max_rate: float = 3600.0,
        acceleration: float = 360.0,
        steps_per_degree: float = 250.0,
        homing: bool = False,
        unplug_after_moves: int | None = None,
        silent_after_moves: int | None = None,
        error_on: dict[str, int] | None = None,
        delay_on: dict[str, float] | None = None,
        drop_on: tuple[str, ...] = (),
        alarm_on: dict[str, int] | None = None,
        garbage_every: int = 0,
        random_state: int | None = None,
        clock=time.monotonic,
    ):
        self.config = dict(locals())
        del self.config["self"], self.config["clock"]
        self.instant = bool(instant)
        self.settings = dict(GRBL_DEFAULTS)
        for i in range(3):
            self.settings[100 + i] = float(steps_per_degree)
            self.settings[110 + i] = float(max_rate)
            self.settings[120 + i] = float(acceleration)
        self.settings[22] = int(bool(homing))
        self.unplug_after_moves = unplug_after_moves
        self.silent_after_moves = silent_after_moves
        self.error_on = _pairs(error_on or {}, int)
        self.delay_on = _pairs(delay_on or {}, float)
        self.drop_on = tuple(normalize_line(k) for k in drop_on if normalize_line(k))
        self.alarm_on = _pairs(alarm_on or {}, int)
        self.garbage_every = int(garbage_every)
        self._random = random.Random(random_state)
        self._clock = clock
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self.plugged, self.unplugged_at = True, None
        self.silent, self.silent_at = False, None  # link up, nothing gets through (brown-out)
        self.rx_peak = self.rx_overruns = self.moves = self.responses = 0
        self._rx = bytearray()
        self._out: collections.deque[tuple[float, bytes]] = collections.deque()
        self._pos = np.zeros(3)
        self._coords = np.zeros((6, 3))  # G54..G59, kept through resets (EEPROM)
        self._planner: collections.deque[_Block] = collections.deque()
        self._segment: _Segment | None = None
        self._events: list = []
        self._event_ids = itertools.count()
        now = clock()
        self._state = "Alarm" if homing else "Idle"
        self._reset_parser(now)
        self._boot_messages(now)

    # ----------------------------------------------------------------- transport side
    def receive(self, data: bytes) -> None:
        """Bytes the host wrote: real-time commands act at once, the rest fill the RX buffer."""
        with self._lock:
            if not self.plugged or self.silent:
                return
            now = self._clock()
            self._service(now)
            dropped = 0
            for byte in data:
                if byte == 0x18:
                    self._soft_reset(now)
                elif byte == 0x3F:  # '?'
                    self._emit_status(now)
                elif byte == 0x21:  # '!'
                    self._feed_hold(now)
                elif byte == 0x7E:  # '~'
                    self._cycle_start(now)
                elif byte == 0x85:
                    self._jog_cancel(now)
                elif byte >= 0x80:
                    continue  # other real-time overrides: not simulated
                elif len(self._rx) >= RX_CAPACITY:
                    dropped += 1
                else:
                    self._rx.append(byte)
                    self.rx_peak = max(self.rx_peak, len(self._rx))
                    if byte in (10, 13):  # the main loop takes each line as it completes
                        self._service(now)
            if dropped:
                self.rx_overruns += dropped
                log.error("RX buffer overrun: %d bytes beyond %d dropped", dropped, RX_CAPACITY)
            self._service(now)
            self._changed.notify_all()

    def read_output(self) -> bytes:
        """What the firmware has printed by now (empty while unplugged)."""
        with self._lock:
            if not self.plugged:
                return b""
            if self.silent:
                self._service(self._clock())
                return b""
            now = self._clock()
            self._service(now)
            out = bytearray()
            while self._out and self._out[0][0] <= now:
                out += self._out.popleft()[1]
            return bytes(out)

    def next_event_delay(self) -> float | None:
        """Seconds until something changes on its own (motion end, delayed answer…), or None."""
        with self._lock:
            now = self._clock()
            times = [t for t, _ in self._out if t > now][:1] + [self._stall_until, self._wake_at]
            if self._segment is not None:
                times.append(self._segment.end_time)
            if self._events:
                times.append(self._events[0][0])
            future = [t - now for t in times if t > now]
            return min(future) if future else None

    def wait(self, timeout: float) -> None:
        """Block until `receive` or `plug` ran, the next timed event, or ``timeout`` s."""
        with self._changed:
            delay = self.next_event_delay()
            self._changed.wait(timeout if delay is None else min(timeout, delay))

    def plug(self) -> None:
        """Connect the cable (or bring a silent link back); anything printed or sent while
        unplugged is lost."""
        with self._lock:
            if not self.plugged or self.silent:
                self.plugged, self.silent = True, False
                self._rx.clear()
                self._out.clear()
            self._changed.notify_all()

    def unplug(self, at: float | None = None) -> None:
        """Pull the cable; the firmware keeps running (an externally powered board)."""
        with self._lock:
            if self.plugged:
                self.plugged, self.unplugged_at = False, self._clock() if at is None else at
                log.info("simulated GRBL cable unplugged")
            self._changed.notify_all()

    def go_silent(self, at: float | None = None) -> None:
        """The link stays up but nothing passes either way (a board that lost power behind a
        USB bridge that stays enumerated, a network bridge whose far side died)."""
        with self._lock:
            if not self.silent:
                self.silent, self.silent_at = True, self._clock() if at is None else at
                log.info("simulated GRBL link gone silent")
            self._changed.notify_all()

    def emit_garbage(self, data: bytes) -> None:
        """Print raw bytes now (line noise, a stale banner from before the host connected)."""
        with self._lock:
            self._emit_raw(data, self._clock())

    def trigger_alarm(self, code: int) -> None:
        """Raise ``ALARM:code`` now, as a limit switch would (1 and 2 then need a reset)."""
        with self._lock:
            now = self._clock()
            self._service(now)
            self._alarm(code, now)

    def position_degrees(self, axis: str = "X") -> float:
        """The table's true machine angle now (whole steps), from the motion profile."""
        with self._lock:
            now = self._clock()
            self._service(now)
            return float(self._quantize(self._position(now))["XYZ".index(axis)])

    @property
    def state(self) -> str:
        """The state as a status report shows it (``"Idle"``, ``"Hold:1"``…)."""
        with self._lock:
            self._service(self._clock())
            if self._state == "Hold":
                return f"Hold:{0 if self._hold_complete else 1}"
            return self._state

    # ----------------------------------------------------------------- time
    def _service(self, now: float) -> None:
        while True:
            self._fire_due_events(now)
            self._advance(now)
            if not self._process_lines(now):
                break
        self._fire_due_events(now)

    def _fire_due_events(self, now: float) -> None:
        while self._events and self._events[0][0] <= now:
            t, _, kind, arg = heapq.heappop(self._events)
            self._advance(t)
            if kind == "unplug":
                self.unplug(at=t)
            elif kind == "silence":
                self.go_silent(at=t)
            else:
                self._alarm(arg, t)

    def _advance(self, now: float) -> None:
        while True:
            seg = self._segment
            if seg is not None:
                if now < seg.end_time:
                    return
                self._pos, self._segment = seg.end.copy(), None
                self._finish_segment(seg.kind, seg.end_time)
            elif self._planner and self._state in _STATES_THAT_RUN_BLOCKS:
                self._start_block(max(self._planner[0].planned_at, self._last_stop))
            else:
                return

    def _start_block(self, t0: float) -> None:
        block = self._planner[0]
        delta = block.target - self._pos
        distance = float(np.linalg.norm(delta))
        self._state = {"run": "Run", "jog": "Jog", "home": "Home"}[block.kind]
        if self.instant or distance < 1e-12:
            unit, profile = np.zeros(3), Profile(0.0, 0.0, 1.0, 0.0)
        else:
            unit = delta / distance
            rate = min(block.rate, self._axis_limit(unit, 110))
            profile = Profile.trapezoid(distance, rate / 60.0, self._axis_limit(unit, 120))
        self._segment = _Segment(self._pos.copy(), unit, profile, t0, block.kind, block.target)
        if block.event is not None:
            when = t0 + profile.duration / 2
            heapq.heappush(self._events, (when, next(self._event_ids), *block.event))
            block.event = None

    def _finish_segment(self, kind: str, t_end: float) -> None:
        self._last_stop = t_end
        if kind == "hold":
            self._hold_complete = True
            return
        if kind == "cancel":
            self._planner.clear()
            self._plan_pos = self._pos.copy()
        else:
            self._planner.popleft()
        if not self._planner:
            self._state = "Idle"

    def _axis_limit(self, unit: np.ndarray, base: int) -> float:
        """Largest rate (base 110) or acceleration (120) along ``unit`` that no axis exceeds."""
        return min(self.settings[base + i] / abs(u) for i, u in enumerate(unit) if abs(u) > 1e-12)

    def _position(self, now: float) -> np.ndarray:
        return self._pos.copy() if self._segment is None else self._segment.at(now)[0]

    def _quantize(self, pos: np.ndarray) -> np.ndarray:
        steps = np.array([self.settings[100 + i] for i in range(3)])
        return np.round(pos * steps) / steps

    def _motion_done(self) -> bool:
        return self._segment is None and not self._planner

    # ----------------------------------------------------------------- output
    def _emit_raw(self, data: bytes, at: float) -> None:
        self._out.append((max(at, self._out[-1][0]) if self._out else at, data))

    def _emit(self, text: str, at: float) -> None:
        self._emit_raw(text.encode("latin-1") + b"\r\n", at)

    def _respond(self, line: str, code: int, at: float) -> None:
        """``ok`` or ``error:N`` for ``line``, through the drop/delay/garbage faults."""
        if any(key in line for key in self.drop_on):
            log.info("simulated fault: dropping the answer to %r", line)
            return
        delay = next((d for key, d in self.delay_on.items() if key in line), 0.0)
        if delay:
            at = self._stall_until = at + delay
        self.responses += 1
        if self.garbage_every and self.responses % self.garbage_every == 0:
            noise = bytes(self._random.choice(range(0x80, 0x100)) for _ in range(12))
            self._emit_raw(noise[:6] + b"<ok>" + noise[6:] + b"\r\n", at)
        self._emit("ok" if code == 0 else f"error:{code}", at)

    def _emit_status(self, now: float) -> None:
        """A status report, printed ahead of answers that a delay fault still holds back."""
        state = self._state
        if state == "Hold":
            state = f"Hold:{0 if self._hold_complete else 1}"
        pos = self._quantize(self._position(now))
        speed = 0.0 if self._segment is None else self._segment.at(now)[1] * 60.0
        mask, wco = int(self.settings[10]), self._wco()
        fields = [state, ("MPos:" if mask & 1 else "WPos:") + _fmt(pos if mask & 1 else pos - wco)]
        if mask & 2:
            free_blocks, free_bytes = (
                PLANNER_BLOCKS - len(self._planner),
                RX_BUFFER_SIZE - len(self._rx),
            )
            fields.append(f"Bf:{free_blocks},{free_bytes}")
        fields.append(f"FS:{speed:.0f},0")
        if self._pins:
            fields.append(f"Pn:{self._pins}")
        busy = self._state in ("Run", "Hold", "Jog", "Home")
        if self._wco_counter > 0:
            self._wco_counter -= 1
        else:
            self._wco_counter = (30 if busy else 10) - 1
            self._ov_counter = self._ov_counter or 1
            fields.append("WCO:" + _fmt(wco))
        if self._ov_counter > 0:
            self._ov_counter -= 1
        else:
            self._ov_counter = (20 if busy else 10) - 1
            fields.append("Ov:100,100,100")
        index = next((i for i, (t, _) in enumerate(self._out) if t > now), len(self._out))
        self._out.insert(index, (now, ("<" + "|".join(fields) + ">\r\n").encode()))

    # ----------------------------------------------------------------- resets and alarms
    def _reset_parser(self, now: float) -> None:
        self._motion, self._absolute, self._inches, self._feed = 0, True, False, 0.0
        self._coord_index, self._g92 = 0, np.zeros(3)
        self._plan_pos = self._pos.copy()
        self._busy = None
        self._stall_until = self._wake_at = 0.0
        self._last_stop = now
        self._hold_complete = self._hold_from_motion = self._critical = False
        self._wco_counter = self._ov_counter = 0
        self._pins = ""

    def _boot_messages(self, now: float) -> None:
        self._emit("", now)
        self._emit(BANNER, now)
        if self._state == "Alarm":
            self._emit(LOCK_MESSAGE, now)

    def _soft_reset(self, now: float) -> None:
        moving = self._state in ("Run", "Jog", "Home") or (
            self._state == "Hold" and self._hold_from_motion
        )
        homing = self._state == "Home"
        self._pos = self._position(now)
        self._segment = None
        self._planner.clear()
        self._events.clear()
        self._rx.clear()
        self._out = collections.deque(item for item in self._out if item[0] <= now)
        if moving:
            self._emit(f"ALARM:{6 if homing else 3}", now)
        self._state = "Alarm" if moving or self._state == "Alarm" else "Idle"
        self._reset_parser(now)
        self._boot_messages(now)

    def _alarm(self, code: int, now: float) -> None:
        self._pos = self._position(now)
        self._segment, self._busy = None, None
        self._planner.clear()
        self._plan_pos = self._pos.copy()
        self._state, self._last_stop = "Alarm", now
        self._emit(f"ALARM:{code}", now)
        if code in CRITICAL_ALARMS:  # GRBL blocks every line until a reset
            self._emit("[MSG:Reset to continue]", now)
            self._critical = True
            self._pins = "X" if code == 1 else ""

    # ----------------------------------------------------------------- real-time commands
    def _feed_hold(self, now: float) -> None:
        if self._state == "Jog":
            self._jog_cancel(now)
        elif self._state == "Run":
            self._decelerate(now, "hold")
            self._state, self._hold_complete, self._hold_from_motion = "Hold", False, True
        elif self._state == "Idle":
            self._state, self._hold_complete, self._hold_from_motion = "Hold", True, False

    def _decelerate(self, now: float, kind: str) -> None:
        seg = self._segment
        pos, speed = seg.at(now)
        accel = seg.profile.accel
        end = pos + seg.unit * (speed * speed / (2 * accel))
        self._segment = _Segment(pos, seg.unit, Profile.stop(speed, accel), now, kind, end)

    def _cycle_start(self, now: float) -> None:
        if self._state == "Hold" and self._hold_complete:  # ignored while still decelerating
            self._state = "Run" if self._planner else "Idle"
            self._hold_from_motion, self._last_stop = False, now
            self._advance(now)

    def _jog_cancel(self, now: float) -> None:
        if self._state == "Jog" and self._segment is not None and self._segment.kind == "jog":
            self._decelerate(now, "cancel")

    # ----------------------------------------------------------------- line processing
    def _process_lines(self, now: float) -> bool:
        consumed = False
        while not self._critical and now >= self._stall_until:
            if self._busy is not None:
                if not self._busy(now):
                    break
                self._busy = None
            end = next((i for i, b in enumerate(self._rx) if b in (10, 13)), -1)
            if end < 0:
                break
            if self._execute(self._rx[:end].decode("latin-1"), now) is _RETRY:
                break
            del self._rx[: end + 1]
            consumed = True
        return consumed

    def _execute(self, raw: str, now: float):
        line = normalize_line(raw)
        fault = next((code for key, code in self.error_on.items() if key in line), None)
        if len(line) > LINE_MAX:
            code = 11
        elif fault is not None:
            log.info("simulated fault: answering error:%d to %r", fault, line)
            code = fault
        elif not line:
            code = 0
        elif self._state in ("Alarm", "Jog") and line[0] != "$":
            code = 9
        else:
            try:
                code = (self._system_command if line[0] == "$" else self._gcode)(line, now)
            except GcodeError as exc:
                code = exc.code
        if code is _RETRY:
            return _RETRY
        if code is not _DEFERRED:
            self._respond(line, code, now)
        return None

    def _after_motion(self, line: str, now: float, dwell: float = 0.0, action=None):
        """Answer ``line`` once the planner is empty and the axes still, after ``dwell`` s."""
        received = now

        def step(t: float) -> bool:
            if not self._motion_done():
                return False
            done_at = max(received, self._last_stop) + dwell
            if t < done_at:
                self._wake_at = done_at
                return False
            if action is not None:
                action()
            self._respond(line, 0, done_at)
            return True

        self._busy = step
        return _DEFERRED

    def _system_command(self, line: str, now: float):
        state = self._state
        if line == "$":
            self._emit(HELP, now)
            return 0
        if line[1] == "J":
            return self._jog(line, now) if line[2:3] == "=" else 3
        if line[1] in "$GCX":
            if len(line) != 2 or line[1] == "C":
                return 3
            if line == "$$":
                if state in ("Run", "Hold"):
                    return 8
                for n, value in sorted(self.settings.items()):
                    text = f"{value:.0f}" if n in _INT_SETTINGS else f"{value:.3f}"
                    self._emit(f"${n}={text}", now)
            elif line == "$G":
                units, dist = (20 if self._inches else 21), (90 if self._absolute else 91)
                self._emit(
                    f"[GC:G{self._motion} G{54 + self._coord_index} G17 G{units} G{dist} G94 M5 M9"
                    f" T0 F{self._feed:.0f} S0]",
                    now,
                )
            elif state == "Alarm":  # $X
                self._emit("[MSG:Caution: Unlocked]", now)
                self._state, self._pins = "Idle", ""
            return 0
        if state not in ("Idle", "Alarm"):
            return 8
        if line == "$#":
            for i, name in enumerate(("G54", "G55", "G56", "G57", "G58", "G59")):
                self._emit(f"[{name}:{_fmt(self._coords[i])}]", now)
            for text in ("[G28:0.000,0.000,0.000]", "[G30:0.000,0.000,0.000]"):
                self._emit(text, now)
            for text in (f"[G92:{_fmt(self._g92)}]", "[TLO:0.000]", "[PRB:0.000,0.000,0.000:0]"):
                self._emit(text, now)
        elif line == "$I":
            self._emit(f"[VER:{VERSION}.{BUILD}:]", now)
            self._emit(f"[OPT:V,{PLANNER_BLOCKS},{RX_BUFFER_SIZE}]", now)
        elif line == "$N":
            self._emit("$N0=", now)
            self._emit("$N1=", now)
        elif line == "$H":
            return self._home(line, now)
        else:
            number = _NUMBER.match(line, 1)
            if number is None:
                return 2
            if line[number.end() : number.end() + 1] != "=":
                return 3
            value = _NUMBER.fullmatch(line, number.end() + 1)
            if value is None:
                return 2
            return self._store_setting(int(float(number.group())), float(value.group()))
        return 0

    def _store_setting(self, number: int, value: float) -> int:
        if value < 0:
            return 4
        if number not in self.settings:
            return 3
        if number == 20 and value and not self.settings[22]:
            return 10
        self.settings[number] = int(value) if number in _INT_SETTINGS else value
        return 0

    def _home(self, line: str, now: float):
        if not self.settings[22]:
            return 5
        self._state, self._pins = "Idle", ""
        self._planner.append(_Block(np.zeros(3), self.settings[25], "home", now))
        self._plan_pos = np.zeros(3)
        return self._after_motion(line, now)

    def _plan(self, target: np.ndarray, rate: float, kind: str, line: str, now: float) -> None:
        self.moves += 1
        event = None
        if self.unplug_after_moves and self.moves == self.unplug_after_moves:
            event = ("unplug", None)
        if self.silent_after_moves and self.moves == self.silent_after_moves:
            event = ("silence", None)
        for key, code in self.alarm_on.items():
            if key in line:
                event = ("alarm", code)
        self._planner.append(_Block(target.copy(), rate, kind, now, event))
        self._plan_pos = target.copy()

    def _wco(self) -> np.ndarray:
        return self._coords[self._coord_index] + self._g92

    def _jog(self, line: str, now: float):
        if self._state not in ("Idle", "Jog"):
            return 8
        groups, values = {}, {}
        for letter, value in split_words(line[3:]):
            if letter == "G" and value in (20, 21, 53, 90, 91):
                group = _G_GROUPS[int(value)]
                if group in groups:
                    return 21
                groups[group] = int(value)
            elif letter in "FXYZ":
                if letter in values:
                    return 25
                if letter == "F" and value < 0:
                    return 4
                values[letter] = value
            else:
                return 16
        if "F" not in values:
            return 22
        axes = {a: values[a] for a in "XYZ" if a in values}
        if not axes:
            return 26
        if len(self._planner) >= PLANNER_BLOCKS:
            return _RETRY
        scale = 25.4 if groups.get(6, 20 if self._inches else 21) == 20 else 1.0
        absolute = groups.get(3, 90 if self._absolute else 91) == 90
        target = self._target(axes, scale, absolute, machine=groups.get(0) == 53)
        self._plan(target, values["F"] * scale, "jog", line, now)
        return 0

    def _target(self, axes: dict, scale: float, absolute: bool, machine: bool) -> np.ndarray:
        target = self._plan_pos.copy()
        for i, axis in enumerate("XYZ"):
            if axis in axes:
                value = axes[axis] * scale
                if machine:
                    target[i] = value
                elif absolute:
                    target[i] = value + self._wco()[i]
                else:
                    target[i] += value
        return target

    def _gcode(self, line: str, now: float):
        groups, mcodes, values = {}, {}, {}
        for letter, value in split_words(line):
            if letter in "GM":
                code = round(value, 1) if letter == "G" else value
                code = int(code) if code == int(code) else code
                table = _G_GROUPS if letter == "G" else _M_GROUPS
                if code not in table:
                    raise GcodeError(20)
                seen = groups if letter == "G" else mcodes
                if table[code] in seen:
                    raise GcodeError(21)
                seen[table[code]] = code
            elif letter in "FIJKLNPRSTXYZ":
                if letter in values:
                    raise GcodeError(25)
                if letter in "FNPST" and value < 0:
                    raise GcodeError(4)
                values[letter] = value
            else:
                raise GcodeError(20)
        nonmodal, motion_word = groups.get(0), groups.get(1)
        axis_command = nonmodal in (10, 92)
        if axis_command and motion_word is not None:
            raise GcodeError(24)
        axes = {a: values[a] for a in "XYZ" if a in values}
        if "N" in values and (values["N"] != int(values["N"]) or values["N"] > 9999999):
            raise GcodeError(27)
        if values.get("T", 0) > 255:
            raise GcodeError(38)
        units = groups.get(6, 20 if self._inches else 21)
        scale = 25.4 if units == 20 else 1.0
        motion = self._motion if motion_word is None else motion_word
        feed = values["F"] * scale if "F" in values else self._feed
        moving = bool(axes) and not axis_command and motion in (0, 1)
        if nonmodal == 53 and motion not in (0, 1):
            raise GcodeError(30)
        if axes and not axis_command and motion == 80:
            raise GcodeError(31)
        if motion_word in (0, 1) and not axes or axis_command and not axes:
            raise GcodeError(26)
        used = set("NFSTXYZ") | ({"P"} if nonmodal in (4, 10) else set())
        if nonmodal in (4, 10) and "P" not in values or nonmodal == 10 and "L" not in values:
            raise GcodeError(28)
        if nonmodal == 10:
            used.add("L")
            if values["L"] not in (2, 20):
                raise GcodeError(20)
            if int(values["P"]) > 6:
                raise GcodeError(29)
        if moving and motion == 1 and feed <= 0:
            raise GcodeError(22)
        if set(values) - used:
            raise GcodeError(36)
        if moving and len(self._planner) >= PLANNER_BLOCKS:
            return _RETRY  # GRBL waits in the planner; the line stays in the RX buffer
        # Execute in GRBL's order: feed, units, coordinate system, distance mode, non-modal, motion.
        self._feed = feed
        self._inches = units == 20
        if 12 in groups:
            self._coord_index, self._wco_counter = groups[12] - 54, 0
        if 3 in groups:
            self._absolute = groups[3] == 90
        if motion_word is not None:
            self._motion = motion_word
        if nonmodal == 4:
            return self._after_motion(line, now, dwell=values["P"])
        if nonmodal == 10:
            index = int(values["P"]) - 1 if values["P"] >= 1 else self._coord_index

            def set_offsets():
                for i, axis in enumerate("XYZ"):
                    if axis in axes:
                        value = axes[axis] * scale
                        if values["L"] == 20:
                            value = self._plan_pos[i] - self._g92[i] - value
                        self._coords[index, i] = value
                self._wco_counter = 0

            return self._after_motion(line, now, action=set_offsets)
        if nonmodal in (92, 92.1):
            for i, axis in enumerate("XYZ"):
                if nonmodal == 92.1:
                    self._g92[i] = 0.0
                elif axis in axes:
                    self._g92[i] = self._plan_pos[i] - self._coords[self._coord_index, i]
                    self._g92[i] -= axes[axis] * scale
            self._wco_counter = 0
        if moving:
            target = self._target(axes, scale, self._absolute, machine=nonmodal == 53)
            self._plan(target, math.inf if motion == 0 else feed, "run", line, now)
        return 0


def _fmt(values) -> str:
    return ",".join("0.000" if f"{v:.3f}" == "-0.000" else f"{v:.3f}" for v in values)


# --------------------------------------------------------------------- construction from URLs
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
