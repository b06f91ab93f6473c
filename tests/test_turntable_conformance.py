"""What every `Turntable` backend must do (like scikit-learn's check_estimator).

Runs on the simulated backends always; on a real turntable when SCANSTATION_TURNTABLE_URL is set
(e.g. ``grbl:///dev/ttyUSB0``), marked ``hardware``. Hardware moves stay within ±60 degrees.
Serial ports are not probed on their own: a GRBL connect soft-resets whatever answers, so the
port of the turntable is named, never guessed.
"""

import os
import urllib.parse

import pytest

import drivers
from drivers import DeviceError, InvalidDeviceURL, MoveAborted, Turntable
from drivers.registry import backend_class
from sim.station import get_station, reset_stations

TOLERANCE = 0.01  # degrees: covers step quantisation of any sane rotary axis
_HARDWARE_URL = os.environ.get("SCANSTATION_TURNTABLE_URL")
BACKENDS = [
    pytest.param("sim://turntable?station=conformance", id="sim-url"),
    pytest.param("sim://turntable?station=conformance&transport=pty", id="sim-pty"),
    pytest.param(
        "sim://turntable?station=conformance&transport=pty&instant=0"
        "&max_rate=14400&accel=3600&feed=14400",  # 240°/s: a 60° move lasts ~0.3 s
        id="sim-realtime",
    ),
    pytest.param(
        _HARDWARE_URL,
        id="hardware",
        marks=[pytest.mark.hardware]
        + ([] if _HARDWARE_URL else [pytest.mark.skip(reason="SCANSTATION_TURNTABLE_URL unset")]),
    ),
]


@pytest.fixture(params=BACKENDS)
def url(request):
    reset_stations()  # a fresh simulated firmware per test
    yield request.param
    reset_stations()


@pytest.fixture
def table(url):
    with drivers.open_turntable(url) as device:
        yield device


def with_param(url: str, extra: str) -> str:
    return url + ("&" if urllib.parse.urlsplit(url).query else "?") + extra


def test_open_gives_an_open_turntable(table):
    assert isinstance(table, Turntable) and table.is_open
    assert "open" in repr(table) and table.url
    assert isinstance(table.angle, float)


def test_close_is_safe_to_repeat(url):
    device = drivers.open_turntable(url)
    device.close()
    device.close()
    assert not device.is_open and "closed" in repr(device)
    with pytest.raises(DeviceError):
        device.move_to(1)
    with drivers.open_turntable(url) as again:  # the port is free again
        assert again.is_open
    assert not again.is_open


def test_home_zeroes_the_angle(table):
    table.move_to(12.5)
    table.home()
    assert table.angle == pytest.approx(0, abs=TOLERANCE)
    table.move_to(0)
    assert table.angle == pytest.approx(0, abs=TOLERANCE)


@pytest.mark.parametrize("targets", [(10, 45.5, -30, 0)])
def test_move_to_reaches_each_target(table, targets):
    table.home()
    for target in targets:
        table.move_to(target)
        assert table.angle == pytest.approx(target, abs=TOLERANCE)


def test_move_by_accumulates(table):
    table.home()
    for _ in range(3):
        table.move_by(15)
    assert table.angle == pytest.approx(45, abs=TOLERANCE)
    table.move_by(-45)
    assert table.angle == pytest.approx(0, abs=TOLERANCE)


def test_wait_until_still_when_still(table):
    table.home()
    table.move_to(20)
    table.wait_until_still(timeout=5)
    assert table.angle == pytest.approx(20, abs=TOLERANCE)


def test_stop_when_still_keeps_the_angle_and_allows_moves(table):
    table.home()
    table.move_to(20)
    table.stop()
    assert table.angle == pytest.approx(20, abs=TOLERANCE)
    table.move_to(25)
    assert table.angle == pytest.approx(25, abs=TOLERANCE)


def test_unknown_url_parameter_is_rejected(url):
    with pytest.raises(InvalidDeviceURL):
        backend_class("turntable", url).from_url(with_param(url, "bogus_parameter=1"))


def test_simulated_station_follows_the_table(table, url):
    if not url.startswith("sim://"):
        pytest.skip("simulated backends only")
    station = get_station("conformance")
    start = station.angle_degrees()
    table.move_by(33)
    assert station.angle_degrees() == pytest.approx(start + 33, abs=TOLERANCE)


def _moves_in_real_time(url: str) -> bool:
    return not url.startswith("sim://") or "instant=0" in url


def _start_move(table, target):
    import threading

    outcome = {}

    def move():
        try:
            table.move_to(target)
        except DeviceError as exc:
            outcome["error"] = exc

    mover = threading.Thread(target=move)
    mover.start()
    return mover, outcome


def _wait_until_moving(table, start, timeout=5.0):
    import time

    deadline = time.monotonic() + timeout
    while abs(table.angle - start) < 0.5:
        assert time.monotonic() < deadline, "the table never started moving"
        time.sleep(0.005)


def test_stop_mid_move_halts_between_start_and_target_then_moves_again(table, url):
    if not _moves_in_real_time(url):
        pytest.skip("instant backend: there is no 'mid-move'")
    table.home()
    mover, outcome = _start_move(table, 60)
    _wait_until_moving(table, 0)
    table.stop()
    mover.join(10)
    assert not mover.is_alive()
    assert isinstance(outcome.get("error"), MoveAborted)  # the interrupted move says so
    stopped = table.angle
    assert 0 < stopped < 60
    assert table.referenced  # a controlled stop keeps the angle
    table.wait_until_still(timeout=5)
    assert table.angle == pytest.approx(stopped, abs=TOLERANCE)  # it stays where it stopped
    table.move_to(5)
    assert table.angle == pytest.approx(5, abs=TOLERANCE)


def test_emergency_stop_mid_move_raises_then_moves_again(table, url):
    if not _moves_in_real_time(url):
        pytest.skip("instant backend: there is no 'mid-move'")
    table.home()
    mover, outcome = _start_move(table, 60)
    _wait_until_moving(table, 0)
    table.emergency_stop()
    mover.join(10)
    assert not mover.is_alive() and isinstance(outcome.get("error"), MoveAborted)
    assert 0 < table.angle < 60
    table.move_to(5)  # allowed, the angle may be off until home()
    assert table.angle == pytest.approx(5, abs=TOLERANCE)
    table.home()
    assert table.referenced


def _simulated_homing(url: str, extra: str) -> str:
    if not url.startswith("sim://"):
        pytest.skip("needs a table with homing switches; simulated backends only")
    if "instant=0" in url:
        extra += "&time_scale=200"  # stock homing rates: a minute of simulated time
    return with_param(url, "homing=1&power_on_angle=90" + extra)


def test_homing_at_connect_references_the_table(url):
    with drivers.open_turntable(_simulated_homing(url, "")) as table:
        assert table.referenced
        assert get_station("conformance").angle_degrees() % 360 == pytest.approx(359)
        table.move_to(10)
        assert table.angle == pytest.approx(10, abs=TOLERANCE)


def test_home_0_unlocks_without_homing(url, caplog):
    with caplog.at_level("WARNING"), drivers.open_turntable(_simulated_homing(url, "&home=0"))\
            as table:
        assert not table.referenced and "unreferenced" in caplog.text
        assert get_station("conformance").angle_degrees() == pytest.approx(90)
        table.move_to(10)
        table.home()
        assert table.referenced and table.angle == pytest.approx(0, abs=TOLERANCE)


def test_wait_until_still_times_out_while_moving(table, url):
    if not _moves_in_real_time(url):
        pytest.skip("instant backend: never moving")
    from drivers import DeviceTimeout

    table.home()
    mover, outcome = _start_move(table, 60)
    try:
        _wait_until_moving(table, 0)
        with pytest.raises(DeviceTimeout):
            table.wait_until_still(timeout=0.01)
    finally:
        mover.join(30)
    assert "error" not in outcome and table.angle == pytest.approx(60, abs=TOLERANCE)
