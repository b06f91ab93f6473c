"""GRBL 1.1 serial protocol: response classification, status reports, error and alarm tables.

Pure functions and constants shared by the driver (`drivers.grbl`) and the firmware simulator
(`sim.grbl_firmware`). Tables follow the GRBL wiki (doc/csv/error_codes_en_US.csv,
alarm_codes_en_US.csv) for GRBL 1.1h.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import re

from .errors import FirmwareAlarm, HomingFailed

#: Real-time commands: picked off the serial stream by the firmware, never buffered, no `ok`.
SOFT_RESET = b"\x18"
STATUS_QUERY = b"?"
FEED_HOLD = b"!"
CYCLE_START = b"~"
JOG_CANCEL = b"\x85"

#: Bytes in GRBL's serial receive ring buffer (`[OPT:…,15,128]`). A ring buffer keeps one slot
#: free, so at most ``RX_BUFFER_SIZE - 1`` bytes may be outstanding.
RX_BUFFER_SIZE = 128
#: Planner blocks (`[OPT:V,15,128]`).
PLANNER_BLOCKS = 15
#: Characters a line may hold after whitespace and comments are removed (LINE_BUFFER_SIZE - 1).
LINE_MAX = 79

ERROR_CODES: dict[int, str] = {
    1: "Expected command letter: G-code words consist of a letter and a value",
    2: "Bad number format: missing the expected G-code word value or invalid number",
    3: "Invalid statement: '$' system command not recognized or supported",
    4: "Value < 0: negative value received for an expected positive value",
    5: "Setting disabled: homing is not enabled via settings",
    6: "Value < 3 usec: minimum step pulse time must be greater than 3 usec",
    7: "EEPROM read fail: using defaults",
    8: "Not idle: '$' command cannot be used unless Grbl is IDLE",
    9: "G-code lock: G-code commands are locked out during alarm or jog state",
    10: "Homing not enabled: soft limits cannot be enabled without homing",
    11: "Line overflow: max characters per line exceeded, line not executed",
    12: "Step rate > 30kHz: setting would exceed the maximum step rate",
    13: "Check door: safety door detected as opened",
    14: "Line length exceeded: build info or startup line too long for EEPROM",
    15: "Travel exceeded: jog target exceeds machine travel, jog ignored",
    16: "Invalid jog command: no '=' or prohibited g-code",
    17: "Setting disabled: laser mode requires PWM output",
    20: "Unsupported command: unsupported or invalid g-code command in block",
    21: "Modal group violation: more than one command from the same modal group",
    22: "Undefined feed rate: feed rate has not yet been set or is undefined",
    23: "G-code command in block requires an integer value",
    24: "More than one g-code command that requires axis words found in block",
    25: "Repeated g-code word found in block",
    26: "No axis words found in block for a command or modal state which requires them",
    27: "Line number value is invalid",
    28: "G-code command is missing a required value word",
    29: "G59.x work coordinate systems are not supported",
    30: "G53 only allowed with G0 and G1 motion modes",
    31: "Axis words found in block when no command or modal state uses them",
    32: "G2 and G3 arcs require at least one in-plane axis word",
    33: "Motion command target is invalid",
    34: "Arc radius value is invalid",
    35: "G2 and G3 arcs require at least one in-plane offset word",
    36: "Unused value words found in block",
    37: "G43.1 dynamic tool length offset is not assigned to the tool length axis",
    38: "Tool number greater than max supported value",
}

ALARM_CODES: dict[int, str] = {
    1: "Hard limit triggered; machine position is likely lost, re-homing is recommended",
    2: "Soft limit: motion target exceeds machine travel; position retained",
    3: "Abort during cycle: reset while in motion; position is likely lost",
    4: "Probe fail: probe not in the expected initial state",
    5: "Probe fail: probe did not contact the workpiece",
    6: "Homing fail: the active homing cycle was reset",
    7: "Homing fail: safety door was opened during homing",
    8: "Homing fail: pull-off travel failed to clear the limit switch",
    9: "Homing fail: could not find the limit switch within search distance",
    10: "Homing fail: could not find the second limit switch for self-squaring",
}

#: Alarms after which GRBL blocks every line until a soft reset (`[MSG:Reset to continue]`).
CRITICAL_ALARMS = frozenset({1, 2, 10})

#: What to check after each homing alarm (gnea/grbl limits.c, limits_go_home).
HOMING_ADVICE: dict[int, str] = {
    6: "the cycle was stopped or reset before it finished; run home() again",
    7: "the safety door opened during homing; close it and run home() again",
    8: "the pull-off ($27) did not clear the switch; raise $27 or check the switch",
    9: "no switch closed within 1.5 x the max travel ($130-$132) of an axis of the cycle "
       "(stock 1.1h homes Z, then X and Y, and needs a switch on each); check the switches and "
       "their wiring, or set $22=0 on a table without a switch",
    10: "the second switch of a dual axis was not found; check its wiring",
}
#: GRBL's homing search reaches 1.5 x the max travel, the locate phase 5 x the pull-off.
HOMING_SEARCH_SCALAR, HOMING_LOCATE_SCALAR = 1.5, 5.0


def alarm_error(code: int | None, command: str | None = None):
    """The exception for ``ALARM:code``: `HomingFailed` (with what to check) for 6-10, else
    `FirmwareAlarm`."""
    code = 1 if code is None else code
    if code in HOMING_ADVICE:
        return HomingFailed(code, f"{alarm_meaning(code)}: {HOMING_ADVICE[code]}", command)
    return FirmwareAlarm(code, alarm_meaning(code), command)


def homing_duration(settings: dict[int, float]) -> float:
    """Longest time in seconds a ``$H`` can take with these ``$`` settings, whatever the
    compiled cycles: every axis (X, Y, Z) searches 1.5 x its max travel ($130-$132) at the seek
    rate $25 (capped by $110-$112, accelerating at $120-$122), pulls off $27, locates the switch
    within 5 x $27 at the feed rate $24 and pulls off again, with the $26 ms debounce after each
    of the four phases. A cycle homing several axes together takes as long as its slowest axis,
    so the sum over axes bounds any grouping (stock 1.1h: Z, then X and Y)."""
    total = 0.0
    for i in range(3):
        rate, accel = settings[110 + i], settings[120 + i]
        seek, feed = min(settings[25], rate), min(settings[24], rate)
        pull = settings[27]
        total += move_duration(HOMING_SEARCH_SCALAR * settings[130 + i], seek, accel)
        total += 2 * move_duration(pull, seek, accel)
        total += move_duration(HOMING_LOCATE_SCALAR * pull, feed, accel)
        total += 4 * settings[26] / 1000.0
    return total


def error_meaning(code: int) -> str:
    return ERROR_CODES.get(code, f"unknown GRBL error {code}")


def alarm_meaning(code: int) -> str:
    return ALARM_CODES.get(code, f"unknown GRBL alarm {code}")


class Kind(enum.Enum):
    OK = "ok"
    ERROR = "error"
    ALARM = "alarm"
    STATUS = "status"  # <Idle|MPos:…>
    BANNER = "banner"  # Grbl 1.1h ['$' for help]
    MESSAGE = "message"  # [MSG:…]
    FEEDBACK = "feedback"  # [GC:…], [VER:…], [OPT:…], [G54:…], [HLP:…]
    SETTING = "setting"  # $110=500.000
    STARTUP = "startup"  # >G54:ok (startup line executed)
    BLANK = "blank"
    UNKNOWN = "unknown"  # garbage, noise, foreign output


@dataclasses.dataclass(frozen=True)
class Response:
    """One classified line from the firmware. ``code`` for errors and alarms; ``status`` for
    status reports; ``text`` is the line without its line ending."""

    kind: Kind
    text: str
    code: int | None = None
    status: StatusReport | None = None


@dataclasses.dataclass(frozen=True)
class StatusReport:
    """A parsed real-time status report. Positions are per axis (X, Y, Z) in machine units."""

    state: str
    substate: int | None
    fields: dict[str, str]
    mpos: tuple[float, ...] | None = None
    wpos: tuple[float, ...] | None = None
    wco: tuple[float, ...] | None = None
    feed: float | None = None
    spindle: float | None = None
    buffer: tuple[int, int] | None = None
    overrides: tuple[int, ...] | None = None
    pins: str = ""

    @property
    def moving(self) -> bool:
        """True while the axes may move (running, jogging, homing, decelerating into a hold)."""
        return self.state in ("Run", "Jog", "Home") or (self.state == "Hold" and self.substate != 0)

    def work_position(self, wco: tuple[float, ...] | None = None) -> tuple[float, ...] | None:
        """WPos, or MPos - WCO using this report's WCO or the last one seen (``wco``)."""
        if self.wpos is not None:
            return self.wpos
        offset = self.wco if self.wco is not None else wco
        if self.mpos is None or offset is None:
            return None
        return tuple(m - o for m, o in zip(self.mpos, offset, strict=False))

    def machine_position(self, wco: tuple[float, ...] | None = None) -> tuple[float, ...] | None:
        """MPos, or WPos + WCO."""
        if self.mpos is not None:
            return self.mpos
        offset = self.wco if self.wco is not None else wco
        if self.wpos is None or offset is None:
            return None
        return tuple(w + o for w, o in zip(self.wpos, offset, strict=False))


def _numbers(text: str | None, kind=float) -> tuple | None:
    return None if text is None else tuple(kind(v) for v in text.split(","))


def parse_status(line: str) -> StatusReport:
    """Parse ``<State[:sub]|Name:v,v,…|…>`` by field name; raise ValueError if malformed."""
    if not (line.startswith("<") and line.endswith(">")):
        raise ValueError(f"not a status report: {line!r}")
    state_text, *parts = line[1:-1].split("|")
    state, _, sub = state_text.partition(":")
    if not state.isalpha():
        raise ValueError(f"bad machine state in {line!r}")
    fields = {}
    for part in parts:
        name, sep, value = part.partition(":")
        if not sep or not name:
            raise ValueError(f"bad status field {part!r} in {line!r}")
        fields[name] = value
    feed_speed = _numbers(fields.get("FS")) or _numbers(fields.get("F"))
    buffer = _numbers(fields.get("Bf"), int)
    return StatusReport(
        state=state,
        substate=int(sub) if sub else None,
        fields=fields,
        mpos=_numbers(fields.get("MPos")),
        wpos=_numbers(fields.get("WPos")),
        wco=_numbers(fields.get("WCO")),
        feed=feed_speed[0] if feed_speed else None,
        spindle=feed_speed[1] if feed_speed and len(feed_speed) > 1 else None,
        buffer=buffer[:2] if buffer else None,
        overrides=_numbers(fields.get("Ov"), int),
        pins=fields.get("Pn", ""),
    )


_BANNER = re.compile(r"^Grbl (\S+) \['\$' for help\]$")
_SETTING = re.compile(r"^\$(\d+)=(-?[\d.]+)")
_NOISE = "".join(map(chr, range(0x20))) + "\x7f"


def clean_line(raw: bytes) -> str:
    """Decode one received line (without its ``\\n``), dropping control bytes at either end."""
    return raw.decode("latin-1").strip(_NOISE + " ")


def parse_response(line: str) -> Response:
    """Classify one line from the firmware (already cleaned of its line ending)."""
    if not line:
        return Response(Kind.BLANK, line)
    if line == "ok":
        return Response(Kind.OK, line)
    head, _, tail = line.partition(":")
    if head in ("error", "ALARM") and tail.isdigit():
        kind = Kind.ERROR if head == "error" else Kind.ALARM
        return Response(kind, line, code=int(tail))
    if line.startswith("<"):
        try:
            return Response(Kind.STATUS, line, status=parse_status(line))
        except ValueError:
            return Response(Kind.UNKNOWN, line)
    if line.startswith("[MSG:") and line.endswith("]"):
        return Response(Kind.MESSAGE, line)
    if line.startswith("[") and line.endswith("]") and ":" in line and line[1:2].isalpha():
        return Response(Kind.FEEDBACK, line)
    if _BANNER.match(line):
        return Response(Kind.BANNER, line)
    if _SETTING.match(line):
        return Response(Kind.SETTING, line)
    if line.startswith(">") and line.endswith(":ok"):
        return Response(Kind.STARTUP, line)
    return Response(Kind.UNKNOWN, line)


def banner_version(line: str) -> str | None:
    """``"1.1h"`` for ``Grbl 1.1h ['$' for help]``, else None."""
    match = _BANNER.match(line)
    return match.group(1) if match else None


def parse_setting(line: str) -> tuple[int, float]:
    """``"$110=500.000"`` -> ``(110, 500.0)``; ValueError otherwise."""
    match = _SETTING.match(line)
    if not match:
        raise ValueError(f"not a setting line: {line!r}")
    return int(match.group(1)), float(match.group(2))


def parse_options(line: str) -> tuple[str, int, int] | None:
    """``"[OPT:V,15,128]"`` -> ``("V", 15, 128)`` (option letters, planner blocks, RX bytes)."""
    if not (line.startswith("[OPT:") and line.endswith("]")):
        return None
    parts = line[5:-1].split(",")
    if len(parts) < 3:
        return None
    try:
        return parts[0], int(parts[1]), int(parts[2])
    except ValueError:
        return None


def format_number(value: float) -> str:
    """A G-code number with GRBL's 3 decimals, without ``-0.000``."""
    text = f"{value:.3f}"
    return "0.000" if text == "-0.000" else text


def move_duration(distance: float, rate: float, acceleration: float) -> float:
    """Seconds for a rest-to-rest trapezoidal move: ``distance`` units at most ``rate``
    units/min, accelerating at ``acceleration`` units/s² (GRBL's planner for a single block)."""
    distance = abs(distance)
    if distance == 0.0:
        return 0.0
    speed = rate / 60.0
    if speed * speed / acceleration >= distance:  # triangle: never reaches ``rate``
        return 2.0 * math.sqrt(distance / acceleration)
    return distance / speed + speed / acceleration
