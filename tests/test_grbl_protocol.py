"""GRBL 1.1 protocol parsing, and the simulator answering as GRBL.md says the real firmware does.

The simulator runs on a fake clock here, so motion timing is checked exactly and instantly.
About 450 lines: one file per protocol, parser and firmware simulator tested side by side.
"""

import math

import pytest

from drivers.grbl_protocol import (
    ALARM_CODES,
    ERROR_CODES,
    Kind,
    alarm_meaning,
    banner_version,
    clean_line,
    error_meaning,
    format_number,
    move_duration,
    parse_options,
    parse_response,
    parse_setting,
    parse_status,
)
from sim.grbl_firmware import BANNER, LOCK_MESSAGE, GrblFirmware
from sim.grbl_gcode import normalize_line
from sim.grbl_motion import Profile
from sim.grbl_options import firmware_options, station_firmware
from sim.station import get_station, reset_stations

# ---------------------------------------------------------------- status reports (GRBL.md shapes)


def test_run_report_with_pins():
    s = parse_status("<Run|MPos:35.572,0.000,0.000|FS:360,0|Pn:PXYZRHS>")
    assert (s.state, s.substate, s.mpos, s.feed, s.spindle) == ("Run", None, (35.572, 0, 0), 360, 0)
    assert s.pins == "PXYZRHS" and s.moving and s.wco is None and s.overrides is None
    assert s.work_position() is None  # no WCO seen yet
    assert s.work_position(wco=(10.0, 0.0, 0.0)) == pytest.approx((25.572, 0, 0))


def test_idle_report_with_overrides():
    s = parse_status("<Idle|MPos:90.000,0.000,0.000|FS:0,0|Ov:100,100,100>")
    assert s.state == "Idle" and not s.moving and s.overrides == (100, 100, 100) and s.pins == ""


@pytest.mark.parametrize(
    "state, substate, moving",
    [("Hold:0", 0, False), ("Hold:1", 1, True), ("Jog", None, True), ("Alarm", None, False)],
)
def test_hold_jog_alarm_states(state, substate, moving):
    s = parse_status(f"<{state}|MPos:1.000,2.000,3.000|FS:0,0>")
    assert s.state == state.split(":")[0] and s.substate == substate and s.moving is moving


def test_fields_are_found_by_name_in_any_order():
    a = parse_status("<Idle|MPos:1.000,2.000,3.000|Bf:15,128|FS:0,0|WCO:1.000,0.000,0.000>")
    b = parse_status("<Idle|WCO:1.000,0.000,0.000|FS:0,0|MPos:1.000,2.000,3.000|Bf:15,128>")
    assert a.mpos == b.mpos == (1, 2, 3) and a.wco == b.wco and a.buffer == b.buffer == (15, 128)
    assert a.work_position() == (0, 2, 3)


def test_wpos_report_gives_machine_position_from_wco():
    s = parse_status("<Idle|WPos:5.000,0.000,0.000|FS:0,0|WCO:85.000,0.000,0.000>")
    assert s.work_position() == (5, 0, 0) and s.machine_position() == (90, 0, 0)


@pytest.mark.parametrize("line", ["<Idle|MPos>", "Idle|MPos:1,2,3", "<|MPos:1,2,3>", "<Idle|:1>"])
def test_malformed_status_raises(line):
    with pytest.raises(ValueError):
        parse_status(line)


@pytest.mark.parametrize(
    "line, kind, code",
    [
        ("ok", Kind.OK, None),
        ("error:20", Kind.ERROR, 20),
        ("ALARM:3", Kind.ALARM, 3),
        ("Grbl 1.1h ['$' for help]", Kind.BANNER, None),
        ("[MSG:'$H'|'$X' to unlock]", Kind.MESSAGE, None),
        ("[MSG:Caution: Unlocked]", Kind.MESSAGE, None),
        ("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", Kind.FEEDBACK, None),
        ("[OPT:V,15,128]", Kind.FEEDBACK, None),
        ("$110=500.000", Kind.SETTING, None),
        (">G54:ok", Kind.STARTUP, None),
        ("", Kind.BLANK, None),
        ("<Idle|MPos:0.000,0.000,0.000|FS:0,0>", Kind.STATUS, None),
        ("<Idle|MPos", Kind.UNKNOWN, None),
        ("error:", Kind.UNKNOWN, None),
        ("okay", Kind.UNKNOWN, None),
        ("\xfe\xff<ok>\x9a", Kind.UNKNOWN, None),
    ],
)
def test_response_classification(line, kind, code):
    response = parse_response(line)
    assert response.kind is kind and response.code == code


def test_clean_line_and_small_parsers():
    assert clean_line(b"\x00\x00ok\r") == "ok"
    assert banner_version("Grbl 1.1h ['$' for help]") == "1.1h" and banner_version("ok") is None
    assert parse_setting("$120=10.000") == (120, 10.0)
    assert (
        parse_options("[OPT:V,15,128]") == ("V", 15, 128) and parse_options("[VER:1.1h:]") is None
    )
    assert format_number(-0.0001) == "0.000" and format_number(12.3456) == "12.346"


def test_error_and_alarm_tables_match_the_grbl_wiki():
    assert set(ERROR_CODES) == set(range(1, 18)) | set(range(20, 39))
    assert set(ALARM_CODES) == set(range(1, 11))
    assert error_meaning(2).startswith("Bad number format")
    assert error_meaning(3).startswith("Invalid statement")
    assert error_meaning(8).startswith("Not idle")
    assert error_meaning(9).startswith("G-code lock")
    assert error_meaning(20).startswith("Unsupported command")
    assert error_meaning(25) == "Repeated g-code word found in block"
    assert "reset while in motion" in alarm_meaning(3)
    assert alarm_meaning(1).startswith("Hard limit")
    assert error_meaning(99) == "unknown GRBL error 99"


def test_move_duration_matches_the_measured_grbl_move():
    # GRBL.md: a 90-unit move at F360 with $120=10 took 15.68 s (90/6 s plus acceleration).
    assert move_duration(90, 360, 10) == pytest.approx(15.6)
    assert abs(move_duration(90, 360, 10) - 15.68) < 0.1
    assert move_duration(1, 3600, 10) == pytest.approx(2 * math.sqrt(0.1))  # never at full rate
    assert move_duration(0, 3600, 10) == 0.0
    profile = Profile.trapezoid(90, 6, 10)
    assert profile.duration == pytest.approx(15.6)
    assert profile.at(profile.duration) == pytest.approx((90, 0))
    assert profile.at(profile.duration / 2)[0] == pytest.approx(45)


# ---------------------------------------------------------------- the simulator on a fake clock


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def talk(firmware, data=b""):
    if data:
        firmware.receive(data)
    return firmware.read_output().decode("latin-1").split("\r\n")[:-1]


@pytest.fixture
def clock():
    return FakeClock()


@pytest.fixture
def slow(clock):
    """GRBL defaults for rates: $110=500 units/min, $120=10 units/s², in real time."""
    return GrblFirmware(instant=False, max_rate=500, acceleration=10, clock=clock)


def test_boot_prints_blank_line_then_banner(clock):
    assert talk(GrblFirmware(clock=clock)) == ["", BANNER]
    assert talk(GrblFirmware(homing=True, clock=clock)) == ["", BANNER, LOCK_MESSAGE]


@pytest.mark.parametrize(
    "line, code",
    [
        ("G99", 20),
        ("X", 2),
        ("$999", 3),
        ("G0 X1 X2", 25),
        ("G0 G1 X1", 21),
        ("G1 X10", 22),
        ("G4", 28),
        ("G1 X1 P2 F100", 36),
        ("G10 L20 P0", 26),
        ("G10 L20 G1 X0", 24),
        ("1", 1),
        ("F-1", 4),
        ("G1 X" + "1" * 90, 11),
        ("$J=G91 X10", 22),
        ("$J=G91 G4 X10 F10", 16),
        ("M62", 20),
        ("$C", 3),
        ("$H", 5),
        ("$100=-1", 4),
    ],
)
def test_errors_as_grbl_answers_them(clock, line, code):
    firmware = GrblFirmware(clock=clock)
    talk(firmware)
    assert talk(firmware, line.encode() + b"\n") == [f"error:{code}"]


def test_ok_comes_at_planning_and_g4_p0_only_when_motion_ends(slow, clock):
    talk(slow)
    assert talk(slow, b"G1 X90 F360\n") == ["ok"]
    assert talk(slow, b"$$\n") == ["error:8"]  # '$' commands are refused during motion
    assert talk(slow, b"G4 P0\n") == []
    clock.t += 0.2  # accelerating at 10 units/s²: 0.2 units at 2 units/s
    assert talk(slow, b"?") == ["<Run|MPos:0.200,0.000,0.000|FS:120,0|WCO:0.000,0.000,0.000>"]
    assert talk(slow, b"$I\n") == []  # G4 holds the line queue until the motion ends
    clock.t += 15.6 - 0.2 - 0.001
    assert talk(slow) == []
    clock.t += 0.002  # 15.6 s = move_duration(90, 360, 10), then $I runs
    assert talk(slow) == ["ok", "[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok"]
    assert talk(slow, b"?")[0].startswith("<Idle|MPos:90.000,0.000,0.000|FS:0,0")


def test_feed_hold_decelerates_then_resume_waits_for_hold_0(slow, clock):
    talk(slow, b"G1 X90 F360\nG4 P0\n")
    clock.t += 5.0  # cruising at 6 units/s since 0.6 s: at 1.8 + 4.4 * 6 = 28.2
    talk(slow, b"!")
    clock.t += 0.2
    assert talk(slow, b"?")[0].startswith("<Hold:1|MPos:29.200,")  # 28.2 + 6*0.2 - 5*0.2**2
    assert talk(slow, b"~?")[0].startswith("<Hold:1|")  # resume ignored while decelerating
    clock.t += 0.41
    assert talk(slow, b"?")[0].startswith("<Hold:0|MPos:30.000,")  # stopped after 1.8 units
    clock.t += 10.0
    assert talk(slow, b"?")[0].startswith("<Hold:0|MPos:30.000,")
    assert talk(slow, b"~") == []
    clock.t += move_duration(60, 360, 10) - 0.001
    assert talk(slow) == []
    clock.t += 0.002
    assert talk(slow) == ["ok"]
    assert slow.position_degrees() == 90.0


def test_reset_during_motion_alarms_and_locks(slow, clock):
    talk(slow, b"G1 X90 F360\n")
    clock.t += 2.0
    assert talk(slow, b"\x18") == ["ALARM:3", "", BANNER, LOCK_MESSAGE]
    assert slow.position_degrees() == pytest.approx(10.2, abs=0.004)  # 1.8 + 1.4 * 6
    assert talk(slow, b"G1 X1 F100\n") == ["error:9"]
    assert talk(slow, b"$X\n") == ["[MSG:Caution: Unlocked]", "ok"]
    assert talk(slow, b"?")[0].startswith("<Idle|MPos:10.200,")
    assert talk(slow, b"\x18") == ["", BANNER]  # reset while idle: no alarm


def test_reset_restores_absolute_mode(clock):
    firmware = GrblFirmware(clock=clock)
    talk(firmware, b"G91\nG0 X10\nG0 X10\n")
    assert firmware.position_degrees() == 20
    talk(firmware, b"\x18G0 X5\n")
    assert firmware.position_degrees() == 5


def test_optional_fields_come_and_go(clock):
    firmware = GrblFirmware(clock=clock)
    talk(firmware)
    reports = [talk(firmware, b"?")[0] for _ in range(12)]
    assert "WCO:" in reports[0] and "Ov:" not in reports[0]
    assert "Ov:" in reports[1] and "WCO:" not in reports[1]
    assert ["WCO:" in r for r in reports].count(True) == 2  # every 10 reports when idle
    talk(firmware, b"G0 X30\nG10 L20 P0 X0\n")
    report = parse_status(talk(firmware, b"?")[0])
    assert report.wco == (30, 0, 0) and report.work_position() == (0, 0, 0)


def test_build_info_and_settings(clock):
    firmware = GrblFirmware(max_rate=1234.5, acceleration=50, steps_per_degree=80, clock=clock)
    talk(firmware)
    assert talk(firmware, b"$I\n") == ["[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok"]
    settings = talk(firmware, b"$$\n")
    assert settings[0] == "$0=10" and settings[-1] == "ok"
    assert {"$100=80.000", "$110=1234.500", "$120=50.000", "$22=0"} <= set(settings)
    assert talk(firmware, b"$110=600\n$$\n").count("$110=600.000") == 1


def test_planner_holds_15_blocks_then_rx_buffer_fills(slow, clock):
    talk(slow)
    lines = b"".join(b"G1 X%d F500\n" % i for i in range(1, 21))
    answers = talk(slow, lines)
    assert answers == ["ok"] * 15  # the 16th waits for room in the planner
    assert slow.rx_peak == sum(len(b"G1 X%d F500\n" % i) for i in range(16, 21))
    clock.t += move_duration(1, 500, 10) + 0.001
    assert talk(slow) == ["ok"]


def test_rx_overrun_drops_bytes_and_is_counted(clock):
    firmware = GrblFirmware(clock=clock)
    firmware.trigger_alarm(1)  # critical: nothing is read until a reset
    assert talk(firmware)[-2:] == ["ALARM:1", "[MSG:Reset to continue]"]
    firmware.receive(b"G0X1\n" * 30)  # 150 bytes
    assert firmware.rx_peak == 128 and firmware.rx_overruns == 150 - 128  # GRBL's 128 bytes
    assert talk(firmware, b"?")[0].startswith("<Alarm|") and "Pn:X" in talk(firmware, b"?")[0]


def test_jog_and_jog_cancel(slow, clock):
    talk(slow)
    assert talk(slow, b"$J=G91 X30 F600\n") == ["ok"]
    clock.t += 0.4
    assert talk(slow, b"?")[0].startswith("<Jog|MPos:0.800,")
    assert talk(slow, b"G1 X1 F10\n") == ["error:9"]
    slow.receive(b"\x85")
    clock.t += 0.6
    assert talk(slow, b"?")[0].startswith("<Idle|MPos:1.600,")


def test_homing_lock_and_cycle(clock):
    firmware = GrblFirmware(homing=True, clock=clock)
    talk(firmware)
    assert talk(firmware, b"G0 X1\n") == ["error:9"]
    assert talk(firmware, b"$H\n") == ["ok"]
    assert firmware.state == "Idle"
    assert firmware.position_degrees() == -1  # GRBL: -$27 (pull-off) once homed, $23=0


def test_units_distance_modes_and_steps(clock):
    firmware = GrblFirmware(clock=clock)
    talk(firmware, b"G20 G0 X1\n")
    assert firmware.position_degrees() == pytest.approx(25.4)
    talk(firmware, b"G21 G91 G0 X-0.4\nG90 G1 X33.333 F100\n")
    assert firmware.position_degrees() == 33.332  # 250 steps/degree: whole steps
    assert normalize_line(" g1 x10 (comment) f100 ; tail") == "G1X10F100"


def test_station_firmware_is_the_station_angle_source():
    reset_stations()
    try:
        firmware = station_firmware("proto-test", instant=True)
        assert get_station("proto-test").angle_source is firmware
        assert station_firmware("proto-test") is firmware
        assert station_firmware("proto-test", instant=True) is firmware
        firmware.receive(b"G0 X42\n")
        assert get_station("proto-test").angle_degrees() == 42
        assert station_firmware("proto-test", instant=False) is not firmware
    finally:
        reset_stations()


def test_firmware_options_from_url_query():
    query = {
        "instant": ["0"],
        "accel": ["90"],
        "error_on": ["X90:33", "G4:20"],
        "drop_on": ["$#"],
        "other": ["1"],
    }
    options = firmware_options(query)
    assert options == {
        "instant": False,
        "acceleration": 90.0,
        "error_on": {"X90": 33, "G4": 20},
        "drop_on": ("$#",),
    }
    assert query == {"other": ["1"]}
    with pytest.raises(ValueError, match="instant"):
        firmware_options({"instant": ["maybe"]})


# ---------------------------------------------------------------- what real 1.1h does (GRBL.md)


@pytest.mark.parametrize("rate, first", [(1.0, ["ok", "ALARM:3"]), (0.0, ["ALARM:3"])])
def test_reset_during_g4_p0_may_answer_its_ok_before_alarm_3(clock, rate, first):
    firmware = GrblFirmware(instant=False, max_rate=500, acceleration=10, clock=clock,
                            reset_ok_rate=rate)
    talk(firmware, b"G1 X90 F360\nG4 P0\n")
    clock.t += 2.0
    assert talk(firmware, b"\x18") == [*first, "", BANNER, LOCK_MESSAGE]


def test_reset_after_a_complete_feed_hold_keeps_the_position_without_alarm(clock):
    slow = GrblFirmware(instant=False, max_rate=500, acceleration=10, clock=clock,
                        reset_ok_rate=0)
    talk(slow, b"G1 X90 F360\nG4 P0\n")
    clock.t += 5.0
    talk(slow, b"!")
    clock.t += 0.5  # 6 units/s at 10 units/s^2: still in 0.6 s
    assert talk(slow, b"?")[0].startswith("<Hold:1|")
    clock.t += 0.2
    assert talk(slow, b"?")[0].startswith("<Hold:0|MPos:30.000,")
    assert talk(slow, b"\x18") == ["", BANNER]  # no ALARM:3, no lock
    assert talk(slow, b"?")[0].startswith("<Idle|MPos:30.000,")
    talk(slow, b"\x18G1 X31 F60\n")  # and the next move runs, without $X
    clock.t += 5
    assert slow.position_degrees() == 31


def test_reset_while_decelerating_into_a_hold_is_still_an_abort(slow, clock):
    talk(slow, b"G1 X90 F360\n")
    clock.t += 5.0
    talk(slow, b"!")
    clock.t += 0.2
    assert talk(slow, b"\x18")[0] == "ALARM:3"


def homing_firmware(clock, **options):
    return GrblFirmware(homing=True, instant=False, clock=clock, max_rate=3600,
                        acceleration=100, **options)


def test_homing_cycles_send_no_status_reports_and_take_every_axis(clock):
    firmware = homing_firmware(clock, power_on_angle=90)  # stock: $25=500, $24=25, $27=1
    talk(firmware)
    assert talk(firmware, b"$H\n?") == []
    clock.t += 30.0
    assert talk(firmware, b"?") == []  # GRBL's homing loop reads no real-time command
    clock.t += 30.0  # Z alone: 270 deg to its switch at 500 deg/min = 32.4 s
    assert talk(firmware) == []
    clock.t += 20.0  # then X and Y together: 32.4 s; each cycle locates ~3.7 s ($24=25)
    lines = talk(firmware)
    assert len(lines) == 2 and lines[0].startswith("<Home|MPos:-1.000,-1.000,-1.000|")
    assert lines[1] == "ok"  # one report (asked for during the cycle), then $H's ok
    assert firmware.state == "Idle"
    assert firmware.position_degrees() % 360 == 359  # 1 deg ($27) short of the switch at 0


def test_homing_time_is_bounded_by_the_sum_over_axes(clock):
    from drivers.grbl_protocol import homing_duration, move_duration

    firmware = homing_firmware(clock, power_on_angle=0.5)  # every switch a whole turn away
    talk(firmware)
    talk(firmware, b"$H\n")
    started = clock.t
    while talk(firmware) != ["ok"]:
        clock.t += 0.05
    took = clock.t - started
    x_only = move_duration(1.5 * 360, 500, 100)  # what the driver used to allow
    assert x_only < took <= homing_duration(firmware.settings)


def test_homing_without_a_switch_alarms_9_and_locks(clock):
    firmware = homing_firmware(clock, switches="X", time_scale=1.0)  # stock cycle: Z first
    talk(firmware)
    assert talk(firmware, b"$H\n") == []
    clock.t += 60
    assert talk(firmware, b"?") == []  # a request made during the cycle
    clock.t += 1.5 * 360 / 500 * 60 - 60 + 0.5  # the whole Z search (64.8 s) finds nothing
    lines = talk(firmware)
    assert lines[0] == "ALARM:9" and lines[1].startswith("<Alarm|MPos:0.000,0.000,540.000|")
    # the $H is answered (real 1.1 firmware: gnea/grbl#126), then homing failures end in a reset
    assert lines[2:] == ["ok", "", BANNER, LOCK_MESSAGE]
    assert firmware.state == "Alarm" and talk(firmware, b"G0 X1\n") == ["error:9"]


def test_reset_during_homing_alarms_6(clock):
    firmware = homing_firmware(clock, power_on_angle=90)
    talk(firmware, b"$H\n")
    clock.t += 3
    assert talk(firmware, b"\x18") == ["ALARM:6", "", BANNER, LOCK_MESSAGE]


def test_a_garbled_status_report_does_not_parse(clock):
    firmware = GrblFirmware(clock=clock, garble_status_every=2)
    talk(firmware)
    first, second = talk(firmware, b"?"), talk(firmware, b"?")
    assert parse_response(first[0]).kind is Kind.STATUS
    assert parse_response(second[0]).kind is Kind.UNKNOWN
