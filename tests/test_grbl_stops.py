"""Stops against the simulated GRBL 1.1h: a stopped move always says so, `stop` decelerates and
keeps the angle, `emergency_stop` is immediate and unreferences it; lost status reports."""

import logging
import time

import pytest
from grbl_rig import rig, run_in_thread, wait_for

from drivers import DeviceTimeout, FirmwareAlarm, MoveAborted

RATES = dict(instant=False, max_rate=7200, acceleration=1200)  # 120 deg/s, 0.1 s to stop


@pytest.mark.parametrize("reset_ok_rate", [1.0, 0.0], ids=["ok-before-alarm", "alarm-only"])
@pytest.mark.parametrize("how", ["stop", "emergency_stop"])
def test_a_stopped_move_always_raises_move_aborted(tmp_path, how, reset_ok_rate):
    """Real 1.1h may answer the waiting G4 P0 with `ok` before ALARM:3 (8 of 30 resets): the
    move must still fail, whatever the order of the lines."""
    with rig(tmp_path, **RATES, reset_ok_rate=reset_ok_rate) as (table, fw, _):
        mover = run_in_thread(table.move_to, 1485)
        wait_for(lambda: fw.position_degrees() > 10)
        getattr(table, how)()
        mover.join()
        assert isinstance(mover.error, MoveAborted), mover.error
        assert mover.error.target == 1485 and "1485" in str(mover.error)
        assert 10 < table.angle < 1485
        table.move_to(table.angle + 5)  # the table is usable again at once


def test_stop_decelerates_and_keeps_the_position_referenced(tmp_path, caplog):
    with rig(tmp_path, **RATES) as (table, fw, _):
        mover = run_in_thread(table.move_to, 1485)
        wait_for(lambda: fw.position_degrees() > 30)  # cruising at 120 deg/s
        at_stop = fw.position_degrees()
        table.stop()
        stopped = table.angle
        mover.join()
        assert isinstance(mover.error, MoveAborted)
        # it decelerated: v^2 / 2a = 6 deg past the position at the call (plus the poll delay)
        assert stopped - at_stop >= 120**2 / (2 * 1200) - 0.01
        assert fw.state == "Idle" and table.referenced  # no ALARM:3, nothing lost
        time.sleep(0.05)
        assert table.angle == stopped == fw.position_degrees()
        with caplog.at_level(logging.INFO, logger="drivers.grbl"):
            table.move_to(stopped + 5)  # no unlock needed
        assert "$X" not in caplog.text and table.angle == pytest.approx(stopped + 5)


def test_emergency_stop_is_immediate_and_unreferences_the_angle(tmp_path, caplog):
    with rig(tmp_path, **RATES) as (table, fw, _):
        mover = run_in_thread(table.move_to, 1485)
        wait_for(lambda: fw.position_degrees() > 30)
        with caplog.at_level(logging.WARNING, logger="drivers.grbl"):
            table.emergency_stop()
        mover.join()
        assert isinstance(mover.error, MoveAborted)
        assert fw.state == "Alarm" and not table.referenced
        assert "unreferenced" in caplog.text
        stopped = table.angle
        time.sleep(0.05)
        assert fw.position_degrees() == stopped  # no deceleration after the reset
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="drivers.grbl"):
            table.move_to(stopped + 5)  # unlocks, and says the angle is unreferenced
        assert "unreferenced" in caplog.text and not table.referenced
        table.home()
        assert table.referenced and table.angle == 0


def test_stop_when_idle_keeps_everything(tmp_path):
    with rig(tmp_path, **RATES) as (table, fw, _):
        table.move_to(30)
        table.stop()
        table.emergency_stop()
        assert fw.state == "Idle" and table.referenced and table.angle == 30


def test_an_alarm_of_its_own_is_not_a_stop(tmp_path):
    with rig(tmp_path, **RATES, alarm_on={"X90": 1}) as (table, _, _):
        with pytest.raises(FirmwareAlarm) as info:
            table.move_to(90)
        assert info.value.code == 1 and not isinstance(info.value, MoveAborted)
        assert not table.referenced  # GRBL: "position is likely lost"


def test_status_asks_again_after_a_garbled_report(tmp_path):
    with rig(tmp_path, garble_status_every=2) as (table, fw, _):
        table.move_to(10)
        assert [table.angle for _ in range(4)] == [10] * 4
        assert fw.reports >= 8  # half of them lost, every read answered


def test_status_gives_up_at_its_timeout_having_retried(tmp_path):
    with rig(tmp_path) as (table, fw, _):
        fw.garble_status_every = 1  # every report from now on is garbled
        before = fw.reports
        with pytest.raises(DeviceTimeout, match="no status report within 0.6 s"):
            table.status(timeout=0.6)
        assert fw.reports - before >= 3  # asked again, not once
