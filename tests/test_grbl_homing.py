"""Homing against the simulated GRBL 1.1h (``$22=1``): the lock at power-up, homing at connect
or ``?home=0``, a timeout that covers every axis's cycle, `angle` during the cycle, alarms 6-9.

The simulator runs the stock cycles (Z, then X and Y) at ``time_scale`` times real time: stock
rates ($25=500 deg/min) make a cycle last about a minute of simulated time."""

import logging

import pytest
from grbl_rig import rig, run_in_thread, wait_for

from drivers import HomingFailed
from drivers.grbl_protocol import homing_duration, move_duration

HOMING = dict(homing=True, instant=False, max_rate=3600, acceleration=100)


def test_homing_enabled_homes_at_connect(tmp_path):
    with rig(tmp_path, **HOMING, time_scale=200, power_on_angle=90) as (table, fw, _):
        assert fw.state == "Idle" and table.referenced
        assert fw.position_degrees() % 360 == pytest.approx(359)  # at the switch, less $27
        assert table.angle == pytest.approx(-1)  # machine -$27, no work offset
        table.move_to(10)
        assert table.angle == pytest.approx(10)


def test_home_0_unlocks_instead_and_warns(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="drivers.grbl"):
        with rig(tmp_path, "&home=0", **HOMING, power_on_angle=90) as (table, fw, _):
            assert fw.state == "Idle" and not table.referenced
            assert fw.position_degrees() == 90  # never moved to a switch
            assert "unreferenced" in caplog.text and "home=0" in caplog.text
            table.move_to(10)
            assert table.angle == 10


def test_the_homing_timeout_covers_every_axis_of_the_cycle(tmp_path):
    """Stock 1.1h homes Z, then X and Y: the old bound (X's search only) was too short."""
    options = dict(HOMING, time_scale=1000, power_on_angle=0.5)  # switches a turn away
    with rig(tmp_path, **options) as (table, fw, _):  # homed at connect: ~94 s simulated
        assert table.referenced and fw.state == "Idle"
        x_only = move_duration(1.5 * table.settings[130], table.settings[25], 100)
        assert table.homing_timeout > homing_duration(table.settings) > 3 * x_only


def test_angle_waits_out_a_homing_cycle(tmp_path):
    """GRBL sends no status report during $H: `angle` waits instead of timing out."""
    options = dict(HOMING, time_scale=100, power_on_angle=90)  # ~0.75 s per run of $H
    with rig(tmp_path, "&home=0&timeout=0.3", **options) as (table, fw, _):
        homing = run_in_thread(table.home)
        readings = []
        wait_for(lambda: fw.state == "Home")
        reader = run_in_thread(lambda: readings.append(table.angle))
        reader.join()
        homing.join()
        assert homing.error is None and reader.error is None
        assert fw.state == "Idle" and table.angle == 0 and table.referenced
        assert len(readings) == 1


def test_a_missing_switch_is_a_clear_homing_error(tmp_path):
    with pytest.raises(HomingFailed) as info:  # stock cycles home Z first: no Z switch here
        with rig(tmp_path, **HOMING, switches="X", time_scale=500):
            pass
    assert info.value.code == 9 and "$22=0" in str(info.value) and "switch" in str(info.value)


def test_stop_during_homing_is_alarm_6(tmp_path):
    with rig(tmp_path, "&home=0", **HOMING, time_scale=100, power_on_angle=90) as (table, fw, _):
        homing = run_in_thread(table.home)
        wait_for(lambda: fw.state == "Home", timeout=1)
        table.stop()
        homing.join()
        assert isinstance(homing.error, HomingFailed) and homing.error.code == 6
        assert not table.referenced and fw.state == "Alarm"
        table.home()  # homing again references the table
        assert table.referenced and table.angle == 0
