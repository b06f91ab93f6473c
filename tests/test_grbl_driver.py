"""The production GRBL driver against the simulated firmware over a real pseudo-terminal."""

import contextlib
import logging
import os
import socket
import threading
import time

import pytest
import serial
from grbl_rig import rig, run_in_thread, wait_for

import drivers
from drivers import (
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceTimeout,
    FirmwareAlarm,
    FirmwareError,
    InvalidDeviceURL,
)
from drivers.grbl import GrblTurntable
from drivers.grbl_protocol import move_duration
from sim.grbl_firmware import GrblFirmware
from sim.serial_ports import PtyTransport, SimGrblSerial
from sim.station import get_station, reset_stations

STEP = 1 / 250  # the simulator's default resolution, degrees


# ---------------------------------------------------------------- connecting


def test_connect_reads_banner_settings_and_angle(tmp_path):
    with rig(tmp_path, max_rate=7200, acceleration=900, steps_per_degree=80) as (table, fw, _):
        assert table.version == "1.1h"
        assert (table.max_rate, table.acceleration, table.settings[100]) == (7200, 900, 80)
        assert table.angle == 0.0 and isinstance(table.angle, float)
        assert table.port.endswith("ttyGRBL") and table.is_open


def test_connect_ignores_stale_banner_and_garbage(tmp_path):
    firmware = GrblFirmware()  # its power-on banner is already waiting in the pty
    firmware.emit_garbage(b"ok\r\nerror:2\r\n\xfe\xff\x00junk\r\nGrbl 1.1h ['$' for help]\r\nhalf")
    with PtyTransport(firmware, link=str(tmp_path / "tty")) as transport:
        with drivers.open_turntable(f"grbl://{transport.port_name}?timeout=1") as table:
            with pytest.raises(FirmwareError) as info:  # answers pair with the right lines
                table.command("$999")
            assert info.value.code == 3
            assert table.command("$G")[0].startswith("[GC:G0 G54")
            table.move_to(12)
            assert table.angle == 12


def test_connect_unlocks_an_alarm(tmp_path):
    with rig(tmp_path, homing=True) as (table, firmware, _):  # homing enabled: starts locked
        assert firmware.state == "Idle" and table.status().state == "Idle"
        table.home()  # runs $H, then zeroes the work angle
        assert table.angle == 0.0
    firmware = GrblFirmware()
    firmware.trigger_alarm(1)  # a hard limit left from a previous session: needs a reset
    with PtyTransport(firmware, link=str(tmp_path / "tty2")) as transport:
        with drivers.open_turntable(f"grbl://{transport.port_name}?timeout=1") as table:
            assert firmware.state == "Idle"
            table.move_to(5)
            assert table.angle == 5


def test_a_simulated_port_link_never_replaces_a_file(tmp_path):
    mine = tmp_path / "notes.txt"
    mine.write_text("mine")
    with pytest.raises(FileExistsError, match="not a symlink"):
        PtyTransport(GrblFirmware(), link=str(mine)).open()
    assert mine.read_text() == "mine"
    stale = tmp_path / "tty"
    stale.symlink_to(tmp_path / "gone")  # a link a killed simulator left: taken over
    with PtyTransport(GrblFirmware(), link=str(stale)) as transport:
        assert os.path.realpath(stale) == os.ttyname(transport._slave)
    assert not os.path.lexists(stale)


def test_no_banner_raises_device_not_found_naming_the_port():
    master, slave = os.openpty()  # a terminal where nothing answers
    name = os.ttyname(slave)
    try:
        started = time.monotonic()
        with pytest.raises(DeviceNotFound, match=name):
            drivers.open_turntable(f"grbl://{name}?timeout=0.3")
        assert time.monotonic() - started < 2.0
    finally:
        os.close(master)
        os.close(slave)
    with pytest.raises(DeviceNotFound, match="/dev/nonexistent-tty"):
        drivers.open_turntable("grbl:///dev/nonexistent-tty")


# ---------------------------------------------------------------- motion


def test_moves_home_and_angle_readback(tmp_path):
    with rig(tmp_path) as (table, firmware, _):
        table.move_to(90)
        assert table.angle == 90 and firmware.position_degrees() == 90
        table.move_by(-30.5)
        assert table.angle == 59.5
        table.move_to(-45.2)
        assert table.angle == pytest.approx(-45.2, abs=1e-9)
        table.home()  # work zero here; the table does not move
        assert table.angle == 0 and firmware.position_degrees() == pytest.approx(-45.2)
        table.move_to(10)
        assert table.angle == 10 and firmware.position_degrees() == pytest.approx(-35.2)
        table.move_to(1 / 3)
        assert abs(table.angle - 1 / 3) <= STEP / 2


def test_move_returns_only_when_the_motion_is_complete(tmp_path):
    with rig(tmp_path, instant=False, max_rate=36000, acceleration=3600) as (table, firmware, _):
        started = time.monotonic()
        table.move_to(90)
        elapsed = time.monotonic() - started
        assert firmware.state == "Idle" and firmware.position_degrees() == 90
        assert elapsed >= move_duration(90, 36000, 3600)  # the ok came at planning, long before


def test_firmware_error_carries_code_meaning_and_command(tmp_path):
    with rig(tmp_path, error_on={"X90": 33}) as (table, _, _):
        with pytest.raises(FirmwareError) as info:
            table.command("G99")
        assert (info.value.code, info.value.command) == (20, "G99")
        assert info.value.meaning.startswith("Unsupported command")
        with pytest.raises(FirmwareError) as info:
            table.move_to(90)
        assert info.value.code == 33 and "X90.000" in info.value.command
        assert info.value.meaning == "Motion command target is invalid"
        table.move_to(45)  # answers still pair with their lines
        assert table.angle == 45


@pytest.mark.parametrize("code", [1, 4])  # 1 (hard limit) needs a reset, 4 (probe) only $X
def test_alarm_raises_firmware_alarm_until_unlocked(tmp_path, code):
    options = dict(instant=False, max_rate=36000, acceleration=7200, alarm_on={"X90": code})
    with rig(tmp_path, **options) as (table, firmware, _):
        with pytest.raises(FirmwareAlarm) as info:
            table.move_to(90)  # the alarm trips half way
        assert info.value.code == code
        assert info.value.meaning.startswith("Hard limit" if code == 1 else "Probe fail")
        assert firmware.position_degrees() == pytest.approx(45, abs=STEP)
        with pytest.raises(FirmwareAlarm, match="unlock"):
            table.move_to(0)  # not silently unlocked
        assert firmware.state == "Alarm"
        table.unlock()
        table.move_to(0)
        assert table.angle == 0 and firmware.state == "Idle"


def test_unlock_right_after_an_alarm(tmp_path):
    options = dict(instant=False, max_rate=36000, acceleration=7200, alarm_on={"X90": 4})
    with rig(tmp_path, **options) as (table, firmware, _):
        with pytest.raises(FirmwareAlarm):
            table.move_to(90)  # its G4 P0 is never answered: the queue must resynchronise
        table.unlock()
        assert firmware.state == "Idle"
        table.send_gcode(["G90 G0 X10", "G4 P0"])
        assert table.angle == 10


def test_feed_hold_and_resume(tmp_path):
    rates = dict(instant=False, max_rate=14400, acceleration=2400)
    with rig(tmp_path, "&margin=0.1", **rates) as (table, fw, _):
        expected = move_duration(180, 14400, 2400)
        mover = run_in_thread(table.move_to, 180)
        wait_for(lambda: fw.position_degrees() > 20)
        table.feed_hold()
        assert table.status().state == "Hold"
        wait_for(lambda: table.status().substate == 0)
        held = table.angle
        time.sleep(expected * 1.25 + 0.2)  # longer than the move's own timeout
        assert table.angle == held and 20 < held < 180 and mover.is_alive()
        table.resume()
        mover.join()
        assert mover.error is None and table.angle == 180


def test_flow_control_keeps_rx_buffer_within_128_bytes(tmp_path):
    rates = dict(instant=False, max_rate=60000, acceleration=60000)
    with rig(tmp_path, **rates) as (table, firmware, _):
        lines = ["G91 G1 X0.500 F60000"] * 40 + ["G90"]
        table.send_gcode(lines)
        table.wait_until_still(timeout=5)
        assert table.angle == 20
        assert firmware.rx_overruns == 0
        assert 100 <= firmware.rx_peak <= 127  # the buffer was used, never overrun
        assert table.peak_outstanding <= 127
    naive = GrblFirmware(**rates)  # control: a client that does not count characters
    with PtyTransport(naive, link=str(tmp_path / "naive")) as transport:
        with serial.serial_for_url(transport.port_name, timeout=0.5) as port:
            port.write("".join(f"{line}\n" for line in lines).encode())
            wait_for(lambda: naive.rx_overruns > 0)


# ---------------------------------------------------------------- faults


def test_unplug_mid_move_raises_disconnected_quickly_then_reconnect(tmp_path):
    rates = dict(instant=False, max_rate=3600, acceleration=3600, unplug_after_moves=1)
    with rig(tmp_path, **rates) as (table, firmware, transport):
        with pytest.raises(DeviceDisconnected) as info:
            table.move_to(90)
        assert time.monotonic() - firmware.unplugged_at < 1.5
        assert isinstance(info.value, ConnectionError)
        with pytest.raises(DeviceDisconnected):
            table.angle  # noqa: B018
        transport.replug()  # the same symlink now leads to a new pty
        table.reconnect()
        assert table.angle == firmware.position_degrees() and firmware.state == "Idle"
        assert 0 < table.angle <= 90


@pytest.mark.parametrize("transport", ["url", "pty"])
def test_a_link_gone_silent_mid_move_is_a_disconnect_not_a_long_timeout(transport):
    """The port stays open but nothing answers (board without power behind its USB bridge):
    the missing status reports give DeviceDisconnected after link_timeout, not the move's
    whole timeout; reconnect then re-reads the position."""
    url = (f"sim://turntable?station=silent-{transport}&transport={transport}&instant=0"
           "&max_rate=3600&accel=3600&silent_after_moves=2&poll=0.02&link_timeout=0.5")
    try:
        with drivers.open_turntable(url) as table:
            table.move_to(1)
            with pytest.raises(DeviceDisconnected, match="no status report for 0.5 s"):
                table.move_to(180)  # 3 s; the link goes silent half-way
            assert table.firmware.silent
            assert time.monotonic() - table.firmware.silent_at < 1.5
            assert table.firmware.position_degrees() < 180  # noticed before the move ended
            with pytest.raises(DeviceDisconnected):
                table.angle  # noqa: B018
            table.reconnect()  # brings the link back first
            assert table.angle == table.firmware.position_degrees()
    finally:
        reset_stations()


def test_socket_closed_mid_move_raises_disconnected():
    firmware = GrblFirmware(instant=False, max_rate=3600, acceleration=3600)
    server = socket.create_server(("127.0.0.1", 0))
    stop, closed_at = threading.Event(), []

    def serve():  # a network serial bridge (ser2net) in front of the firmware
        connection, _ = server.accept()
        connection.settimeout(0.005)
        with connection:
            while not stop.is_set():
                with contextlib.suppress(TimeoutError):
                    firmware.receive(connection.recv(4096))
                connection.sendall(firmware.read_output())
            closed_at.append(time.monotonic())  # before the close: the driver may see it first

    bridge = threading.Thread(target=serve)
    bridge.start()
    try:
        url = f"socket://127.0.0.1:{server.getsockname()[1]}?timeout=1&poll=0.02"
        with drivers.open_turntable(url) as table:
            table.move_to(3)
            assert table.angle == 3
            mover = run_in_thread(table.move_to, 90)
            wait_for(lambda: firmware.position_degrees() > 10)
            stop.set()  # the network link goes down mid-move
            mover.join()
            assert isinstance(mover.error, DeviceDisconnected)
            assert time.monotonic() - closed_at[0] < 1.5
            assert firmware.position_degrees() < 90
    finally:
        stop.set()
        bridge.join()
        server.close()


@pytest.mark.parametrize("transport", ["url", "pty"])
def test_sim_turntable_unplug_and_replug(transport):
    url = (
        f"sim://turntable?station=unplug-{transport}&transport={transport}&instant=0"
        "&max_rate=7200&accel=7200&unplug_after_moves=2&timeout=1&poll=0.02"
    )
    try:
        with drivers.open_turntable(url) as table:
            table.move_to(-1)
            with pytest.raises(DeviceDisconnected):
                table.move_to(90)
            assert time.monotonic() - table.firmware.unplugged_at < 1.5
            table.reconnect()  # plugs the cable back in first
            assert table.angle == table.firmware.position_degrees()
            table.move_to(0)
            assert table.angle == 0 and get_station(f"unplug-{transport}").angle_degrees() == 0
    finally:
        reset_stations()


def test_reconnect_rereads_the_position(tmp_path):
    with rig(tmp_path) as (table, firmware, _):
        table.move_to(30)
        firmware.receive(b"G90 G0 X75\n")  # moved behind the driver's back
        table.reconnect()
        assert table.angle == 75 and table.is_open


def test_dropped_answer_times_out_within_the_bound_then_recovers(tmp_path):
    with rig(tmp_path, "&timeout=0.3&margin=0.2", drop_on=("$#", "X45")) as (table, fw, _):
        started = time.monotonic()
        with pytest.raises(DeviceTimeout):
            table.command("$#")
        assert 0.3 <= time.monotonic() - started < 0.8
        assert table.command("$I")[0] == "[VER:1.1h.20190830:]"  # resynchronised
        started = time.monotonic()
        with pytest.raises(DeviceTimeout):
            table.move_to(45)
        assert time.monotonic() - started < move_duration(45, 3600, 360) * 1.25 + 0.2 + 0.5
        table.move_to(10)
        assert table.angle == 10


def test_delayed_answers(tmp_path):
    with rig(tmp_path, "&timeout=0.5", delay_on={"X45": 0.25, "X50": 0.8}) as (table, _, _):
        started = time.monotonic()
        table.move_to(45)  # late but within the bound
        assert time.monotonic() - started >= 0.25 and table.angle == 45
        with pytest.raises(DeviceTimeout):
            table.move_to(50)
        time.sleep(0.5)  # the late ok arrives and is matched to the abandoned line
        table.move_to(20)
        assert table.angle == 20


def test_garbage_lines_are_logged_not_fatal(tmp_path, caplog):
    with rig(tmp_path, garbage_every=2, random_state=0) as (table, firmware, _):
        with caplog.at_level(logging.WARNING, logger="drivers.grbl"):
            for target in range(0, 100, 10):
                table.move_to(target)
                assert table.angle == target
            firmware.emit_garbage(b"\x00\xfe\xff\x13noise\r\n")
            assert table.command("$G")[0].startswith("[GC:")
    assert "ignoring unexpected line" in caplog.text


# ---------------------------------------------------------------- life cycle and URLs


def test_close_is_safe_to_repeat_and_final(tmp_path):
    with rig(tmp_path) as (table, _, _):
        pass
    table.close()
    assert not table.is_open
    with pytest.raises(DeviceError, match="not open"):
        table.move_to(1)


def test_url_forms():
    table = GrblTurntable.from_url("grbl:///dev/ttyUSB0?baud=9600&axis=y&feed=100&timeout=2")
    assert (table.port, table.baudrate, table.axis, table.feed, table.timeout) == (
        "/dev/ttyUSB0", 9600, "Y", 100, 2
    )  # fmt: skip
    assert GrblTurntable.from_url("grbl://?port=socket://h:1&feed=5").port == "socket://h:1"
    table = GrblTurntable.from_url("socket://h:1?feed=5&logging=debug")
    assert (table.port, table.feed) == ("socket://h:1?logging=debug", 5)
    assert GrblTurntable.from_url("grbl://COM3").port == "COM3"
    for bad in (
        "grbl:///dev/x?bogus=1",
        "grbl:///dev/x?feed=fast",
        "grbl:///dev/x?axis=Q",
        "grbl://",
    ):
        with pytest.raises(InvalidDeviceURL):
            GrblTurntable.from_url(bad)
    assert all(url.startswith("grbl:///dev/tty") for url in GrblTurntable.discover())


def test_steps_per_degree_is_written_when_it_differs(tmp_path):
    with rig(tmp_path, "&steps_per_degree=80") as (table, firmware, _):
        assert firmware.settings[100] == 80 and table.settings[100] == 80


def test_simgrbl_url_handler_is_registered():
    port = serial.serial_for_url("simgrbl://handler-test?instant=1&max_rate=900", timeout=0.5)
    with port:
        assert isinstance(port, SimGrblSerial)
        port.reset_input_buffer()
        port.write(b"$$\n")
        text = port.read_until(b"ok\r\n").decode()
        assert "$110=900.000" in text and text.endswith("ok\r\n")
    with pytest.raises(ValueError, match="bogus"):
        serial.serial_for_url("simgrbl://handler-test?bogus=1")
    reset_stations()


def test_the_station_follows_the_axis_the_driver_turns():
    try:
        with drivers.open_turntable("sim://turntable?station=axis-y&axis=Y") as table:
            table.move_to(33)
            assert table.firmware.position_degrees("Y") == 33
            assert table.firmware.position_degrees("X") == 0
            assert get_station("axis-y").angle_degrees() == 33  # what the camera renders
    finally:
        reset_stations()


def test_a_board_reporting_inches_is_refused_with_the_fix_named():
    try:
        with drivers.open_turntable("sim://turntable?station=inches") as table:
            table.command("$13=1")
            with pytest.raises(DeviceError, match=r"inches \(\$13=1\); set \$13=0"):
                table.reconnect()
    finally:
        reset_stations()


def test_a_move_is_in_degrees_whatever_units_the_firmware_was_left_in(tmp_path):
    # a reset or $H runs GRBL's startup blocks ($N), which may set G20 (inches: 25.4 x)
    with rig(tmp_path, instant=True) as (table, firmware, _):
        table.send_gcode(["G20"])
        table.move_by(10)
        assert table.angle == pytest.approx(10)


def test_a_move_after_queued_lines_starts_where_they_end(tmp_path):
    # send_gcode returns when its lines are planned (GRBL's ok): the table still runs them,
    # and the next move's own timeout (its 1 degree) ran out while they did
    with rig(tmp_path, "&margin=0.2", instant=False, max_rate=7200,
             acceleration=3600) as (table, firmware, _):
        table.send_gcode(["G91 G1 X90 F7200"] * 2)
        assert firmware.state == "Run"
        table.move_by(1)
        assert table.angle == pytest.approx(181)
