"""A GRBL 1.1h firmware simulator: the serial protocol on top of `sim.grbl_gcode` (the G-code
parser) and `sim.grbl_motion` (planner, steppers, machine state), with `sim.grbl_homing`.

The firmware is passive and thread-safe: a transport (`sim.serial_ports`) hands it the bytes the
host wrote (`receive`) and collects what it prints (`read_output`). Motion is a function of the
clock, so the table's angle is exact at any instant without a thread of its own
(`position_degrees`). ``instant=True`` (default) completes every move when it is planned, like
ophyd's ``SimMotor(instant=True)``; ``time_scale=k`` runs the motion k times faster than real time
(rates and timings as GRBL computes them, in less wall time: tests of homing and stops).

System commands: ``$ $$ $# $G $I $N $X $H $J= $n=v``; real-time ``? ! ~ 0x18 0x85``.
``$C``/``$SLP``/``$RST`` answer ``error:3``. Behaviours of the real firmware that the simulator
keeps (docs/GRBL.md): ``$22=1`` starts alarm-locked; no status report during ``$H`` (one comes
when the cycle ends); a reset in a complete feed hold (``Hold:0``) keeps the position without an
alarm; a reset while ``G4 P0`` waits may answer that ``ok`` before ``ALARM:3``
(``reset_ok_rate``). Fault knobs (constructor arguments, URL query parameters through
`firmware_options`) match lines by substring after GRBL's normalisation (upper case, no spaces):
``error_on={"X90": 33}`` answers ``error:33`` to ``G1 X90 F600``.

About 590 lines: one state machine (GRBL's protocol.c, report.c and system.c: serial side,
real-time bytes, line queue, ``$`` commands, resets and alarms, fault knobs) whose parts share
the output queue and the line queue; the G-code parser, the motion and homing are apart.
"""

from __future__ import annotations

import collections
import logging
import random
import threading
import time

import numpy as np

from drivers.grbl_protocol import CRITICAL_ALARMS, LINE_MAX, PLANNER_BLOCKS, RX_BUFFER_SIZE
from sim.grbl_gcode import NUMBER, GcodeError, GcodeParser, normalize_line, parse_jog
from sim.grbl_homing import STOCK_CYCLES, parse_cycles, plan_homing
from sim.grbl_motion import MotionModel

log = logging.getLogger(__name__)

VERSION, BUILD = "1.1h", "20190830"
BANNER = f"Grbl {VERSION} ['$' for help]"
LOCK_MESSAGE = "[MSG:'$H'|'$X' to unlock]"
HELP = "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"
#: Bytes the RX buffer holds: all 128 (GRBL's ring is RX_BUFFER_SIZE + 1 long, one slot kept
#: free; `Bf` reports 128 when empty)
RX_CAPACITY = RX_BUFFER_SIZE
GRBL_DEFAULTS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0, 20: 0, 21: 0,
    22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: 250.0, 101: 250.0, 102: 250.0, 110: 500.0, 111: 500.0, 112: 500.0,
    120: 10.0, 121: 10.0, 122: 10.0, 130: 360.0, 131: 360.0, 132: 360.0,
}  # fmt: skip  (max travel 360: a rotary axis finds its switch within one 1.5-turn search)
_INT_SETTINGS = frozenset(n for n in GRBL_DEFAULTS if n < 100 and n not in (11, 12, 24, 25, 27))
_DEFERRED, _RETRY = object(), object()  # answer later (sync, dwell, homing); planner full


def _pairs(values, kind) -> dict:
    pairs = values.items() if isinstance(values, dict) else (v.rsplit(":", 1) for v in values)
    return {normalize_line(k): kind(v) for k, v in pairs if normalize_line(k)}


def _fmt(values) -> str:
    return ",".join("0.000" if f"{v:.3f}" == "-0.000" else f"{v:.3f}" for v in values)


class GrblFirmware:
    """GRBL 1.1h on a simulated rotary table; 1 unit = 1 degree on every axis.

    max_rate : $110-$112, degrees/min.  acceleration : $120-$122, degrees/s².
    steps_per_degree : $100-$102.  homing : $22 (starts locked; ``$H`` runs ``homing_cycles``,
    stock ``"Z,XY"``, and needs a switch on every axis it homes: ``switches``).
    power_on_angle : the table's true angle when the board powers up at machine position 0
    (the homing switches close at true angles 0 mod 360).
    time_scale : motion runs this many times faster than the wall clock.
    reset_ok_rate : fraction of resets during a ``G4 P0`` wait that answer its ``ok`` first
    (real 1.1h: 8 of 30), drawn from ``random_state``. garble_status_every : every N-th status
    report arrives garbled.
    """

    def __init__(
        self,
        *,
        instant: bool = True,
        max_rate: float = 3600.0,
        acceleration: float = 360.0,
        steps_per_degree: float = 250.0,
        homing: bool = False,
        homing_cycles: str = ",".join(STOCK_CYCLES),
        switches: str = "XYZ",
        power_on_angle: float = 0.0,
        time_scale: float = 1.0,
        reset_ok_rate: float = 0.25,
        unplug_after_moves: int | None = None,
        silent_after_moves: int | None = None,
        error_on: dict[str, int] | None = None,
        delay_on: dict[str, float] | None = None,
        drop_on: tuple[str, ...] = (),
        alarm_on: dict[str, int] | None = None,
        garbage_every: int = 0,
        garble_status_every: int = 0,
        random_state: int | None = None,
        clock=time.monotonic,
    ):
        self.config = dict(locals())
        del self.config["self"], self.config["clock"]
        if not time_scale > 0 or not 0 <= reset_ok_rate <= 1:
            raise ValueError("time_scale must be > 0 and reset_ok_rate within [0, 1]")
        self.homing_cycles = parse_cycles(homing_cycles)
        self.switches = str(switches).upper()
        self.settings = dict(GRBL_DEFAULTS)
        for i in range(3):
            self.settings[100 + i] = float(steps_per_degree)
            self.settings[110 + i] = float(max_rate)
            self.settings[120 + i] = float(acceleration)
        self.settings[22] = int(bool(homing))
        self.offset = np.full(3, float(power_on_angle))
        self.time_scale = float(time_scale)
        self.reset_ok_rate = float(reset_ok_rate)
        self.unplug_after_moves = unplug_after_moves
        self.silent_after_moves = silent_after_moves
        self.error_on = _pairs(error_on or {}, int)
        self.delay_on = _pairs(delay_on or {}, float)
        self.drop_on = tuple(normalize_line(k) for k in drop_on if normalize_line(k))
        self.alarm_on = _pairs(alarm_on or {}, int)
        self.garbage_every = int(garbage_every)
        self.garble_status_every = int(garble_status_every)
        self._random = random.Random(random_state)
        if self.time_scale != 1.0:
            start = clock()
            clock = lambda: start + (time.monotonic() - start) * self.time_scale  # noqa: E731
        self._clock = clock
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self.plugged, self.unplugged_at = True, None
        self.silent, self.silent_at = False, None  # link up, nothing gets through (brown-out)
        self.rx_peak = self.rx_overruns = self.moves = self.responses = self.reports = 0
        self._rx = bytearray()
        self._out: collections.deque[tuple[float, bytes]] = collections.deque()
        now = clock()
        self.motion = MotionModel(self.settings, bool(instant), now,
                                  "Alarm" if homing else "Idle")
        self.parser = GcodeParser()
        self._reset_protocol(now)
        self._boot_messages(now)

    @property
    def instant(self) -> bool:
        return self.motion.instant

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
                    self.motion.feed_hold(now)
                elif byte == 0x7E:  # '~'
                    self.motion.cycle_start(now)
                elif byte == 0x85:
                    self.motion.jog_cancel(now)
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
        """Wall-clock seconds until something changes on its own (motion end, delayed
        answer…), or None."""
        with self._lock:
            now = self._clock()
            times = [t for t, _ in self._out if t > now][:1] + [self._stall_until, self._wake_at]
            future = [t - now for t in times + self.motion.next_change() if t > now]
            return min(future) / self.time_scale if future else None

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
        """The table's true angle now (whole steps), from the motion profile: the machine
        position plus ``power_on_angle`` until a homing cycle finds the switch at 0 (mod 360)."""
        with self._lock:
            now = self._clock()
            self._service(now)
            i = "XYZ".index(axis)
            return float(self.motion.quantize(self.motion.position(now))[i] + self.offset[i])

    @property
    def state(self) -> str:
        """The state as a status report shows it (``"Idle"``, ``"Hold:1"``…)."""
        with self._lock:
            self._service(self._clock())
            return self.motion.report_state()

    # ----------------------------------------------------------------- time
    def _service(self, now: float) -> None:
        while True:
            self._fire_due_events(now)
            self.motion.advance(now)
            if not self._process_lines(now):
                break
        self._fire_due_events(now)

    def _fire_due_events(self, now: float) -> None:
        while (event := self.motion.due_event(now)) is not None:
            t, kind, arg = event
            if kind == "unplug":
                self.unplug(at=t)
            elif kind == "silence":
                self.go_silent(at=t)
            else:
                self._alarm(arg, t)

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
        """A status report, printed ahead of answers that a delay fault still holds back.
        During ``$H`` GRBL's homing loop reads no real-time command: the request waits."""
        if self._homing:
            self._status_requested = True
        else:
            self._write_status(now, self.motion.report_state())

    def _write_status(self, now: float, state: str) -> None:
        motion = self.motion
        pos = motion.quantize(motion.position(now))
        mask, wco = int(self.settings[10]), self.parser.wco()
        fields = [state,
                  ("MPos:" if mask & 1 else "WPos:") + _fmt(pos if mask & 1 else pos - wco)]
        if mask & 2:
            free_blocks = PLANNER_BLOCKS - len(motion.planner)
            fields.append(f"Bf:{free_blocks},{RX_BUFFER_SIZE - len(self._rx)}")
        fields.append(f"FS:{motion.speed(now):.0f},0")
        if self._pins:
            fields.append(f"Pn:{self._pins}")
        busy = motion.state in ("Run", "Hold", "Jog", "Home")
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
        text = "<" + "|".join(fields) + ">"
        self.reports += 1
        if self.garble_status_every and self.reports % self.garble_status_every == 0:
            log.info("simulated fault: garbling status report %d", self.reports)
            text = text[: len(text) // 2] + "\x8f\xfe"  # a line cut short by noise
        index = next((i for i, (t, _) in enumerate(self._out) if t > now), len(self._out))
        self._out.insert(index, (now, (text + "\r\n").encode("latin-1")))

    # ----------------------------------------------------------------- resets and alarms
    def _reset_protocol(self, now: float) -> None:
        self.parser.reset()
        self.motion.planned = self.motion.pos.copy()
        self._busy = None
        self._sync_waiting = self._status_requested = self._homing = False
        self._stall_until = self._wake_at = 0.0
        self.motion.last_stop = now
        self.motion.hold_complete = self.motion.hold_from_motion = False
        self._critical = False
        self._wco_counter = self._ov_counter = 0
        self._pins = ""

    def _boot_messages(self, now: float) -> None:
        self._emit("", now)
        self._emit(BANNER, now)
        if self.motion.state == "Alarm":
            self._emit(LOCK_MESSAGE, now)

    def _soft_reset(self, now: float) -> None:
        motion = self.motion
        moving, homing = motion.moving or self._homing, self._homing
        if self._sync_waiting and self._random.random() < self.reset_ok_rate:
            self._emit("ok", now)  # the waiting G4's `ok` may still go out (mc_reset's order)
        motion.kill(now)
        self._rx.clear()
        self._out = collections.deque(item for item in self._out if item[0] <= now)
        if moving:
            self._emit(f"ALARM:{6 if homing else 3}", now)
        motion.state = "Alarm" if moving or motion.state == "Alarm" else "Idle"
        self._reset_protocol(now)
        self._boot_messages(now)

    def _alarm(self, code: int, now: float) -> None:
        homing, self._homing = self._homing, False
        self.motion.kill(now)
        self._busy = None
        self._sync_waiting = False
        self.motion.state = "Alarm"
        self._emit(f"ALARM:{code}", now)
        if homing:  # the homing cycle ends in a reset (mc_reset): status, banner, lock message
            if self._status_requested:
                self._status_requested = False
                self._write_status(now, "Alarm")
            if code != 6:  # the failed cycle's $H is answered, then the reset (gnea/grbl#126:
                self._emit("ok", now)  # ALARM:9, ok, banner); a reset (6) cuts it short
            self._rx.clear()
            self._reset_protocol(now)
            self._boot_messages(now)
        elif code in CRITICAL_ALARMS:  # GRBL blocks every line until a reset
            self._emit("[MSG:Reset to continue]", now)
            self._critical = True
            self._pins = "X" if code == 1 else ""

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
        elif self.motion.state in ("Alarm", "Jog") and line[0] != "$":
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
        self._sync_waiting = True

        def step(t: float) -> bool:
            if not self.motion.done():
                return False
            done_at = max(received, self.motion.last_stop) + dwell
            if t < done_at:
                self._wake_at = done_at
                return False
            self._sync_waiting = False
            if action is not None:
                action()
            self._respond(line, 0, done_at)
            return True

        self._busy = step
        return _DEFERRED

    def _system_command(self, line: str, now: float):
        state = self.motion.state
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
                self._emit(self.parser.modal_report(), now)
            elif state == "Alarm":  # $X
                self._emit("[MSG:Caution: Unlocked]", now)
                self.motion.state, self._pins = "Idle", ""
            return 0
        if state not in ("Idle", "Alarm"):
            return 8
        if line == "$#":
            for i, name in enumerate(("G54", "G55", "G56", "G57", "G58", "G59")):
                self._emit(f"[{name}:{_fmt(self.parser.coords[i])}]", now)
            for text in ("[G28:0.000,0.000,0.000]", "[G30:0.000,0.000,0.000]"):
                self._emit(text, now)
            for text in (f"[G92:{_fmt(self.parser.g92)}]", "[TLO:0.000]",
                         "[PRB:0.000,0.000,0.000:0]"):
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
            number = NUMBER.match(line, 1)
            if number is None:
                return 2
            if line[number.end() : number.end() + 1] != "=":
                return 3
            value = NUMBER.fullmatch(line, number.end() + 1)
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
        self.motion.state, self._pins = "Idle", ""
        plan = plan_homing(self.motion, self.homing_cycles, self.switches, now, self.offset)
        self._homing = True
        if plan is None:
            self._busy = lambda t: False  # the main loop is in the cycle until the alarm
            return _DEFERRED  # the search ends in ALARM:9 and a reset: no answer

        homed, offset = plan

        def finish():
            self.offset = offset
            self.motion.pos = homed.copy()
            self.motion.planned = homed.copy()
            self._homing = False
            if self._status_requested:  # the report asked for during the cycle
                self._status_requested = False
                self._write_status(self.motion.last_stop, "Home")

        result = self._after_motion(line, now, action=finish)
        self._sync_waiting = False  # a reset aborts homing with ALARM:6, never an `ok`
        return result

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
        self.motion.plan(target, rate, kind, now, event)

    def _jog(self, line: str, now: float):
        if self.motion.state not in ("Idle", "Jog"):
            return 8
        jog = parse_jog(line[3:], self.parser.inches, self.parser.absolute)
        if len(self.motion.planner) >= PLANNER_BLOCKS:
            return _RETRY
        target = self.parser.target(self.motion.planned, jog.axes, jog.scale, jog.absolute,
                                    jog.machine)
        self._plan(target, jog.feed, "jog", line, now)
        return 0

    def _gcode(self, line: str, now: float):
        block = self.parser.parse(line)
        if block.moving and len(self.motion.planner) >= PLANNER_BLOCKS:
            return _RETRY  # GRBL waits in the planner; the line stays in the RX buffer
        move = self.parser.apply(block, self.motion.planned)
        if 12 in block.groups or block.nonmodal in (92, 92.1):
            self._wco_counter = 0
        if block.nonmodal == 4:
            return self._after_motion(line, now, dwell=block.dwell)
        if block.nonmodal == 10:

            def set_origin():
                self.parser.set_origin(block, self.motion.planned)
                self._wco_counter = 0

            return self._after_motion(line, now, action=set_origin)
        if move is not None:
            self._plan(*move, "run", line, now)
        return 0
