"""Turntable timing: the production GRBL driver against the simulated firmware on a pty.

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.turntable [--repeats 300] [--faults 5]

Round trips (``?`` status, one G-code line's ``ok``) through the driver, against a raw pyserial
client on the same pty (the peer: what the link itself costs); and a 360° sequence of 36 moves of
10°, instant and in real time, against the ideal motion time of the trapezoidal profile; and how
long a fault mid-move (cable pulled, or a link gone silent with the port still open) takes to
raise DeviceDisconnected (target: within 1 s); and how a move is stopped: `stop()` (feed hold,
Hold:0, reset) against `emergency_stop()` (reset at once), cruising at $110: time in the call,
distance run after it against the ideal v²/2a, whether the reported angle is the table's true
one afterwards and whether GRBL kept the position (no ALARM:3).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import statistics
import tempfile
import threading
import time

import serial

import drivers
from drivers.grbl_protocol import move_duration
from sim.grbl_firmware import GrblFirmware
from sim.serial_ports import PtyTransport

MAX_RATE, ACCEL = 7200.0, 720.0  # deg/min, deg/s² for the real-time sequence


@contextlib.contextmanager
def pty_table(**firmware_options):
    firmware = GrblFirmware(**firmware_options)
    with tempfile.TemporaryDirectory() as tmp, PtyTransport(firmware, f"{tmp}/tty") as transport:
        url = f"grbl://{transport.port_name}?feed={MAX_RATE}&poll=0.05"
        with drivers.open_turntable(url) as table:
            yield table, transport


def timings(function, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        out.append(time.perf_counter() - start)
    return out


def raw_round_trip(port: serial.Serial, request: bytes, end: bytes) -> None:
    """The peer: write, then read whatever is waiting until the answer's end marker."""
    port.write(request)
    answer = b""
    while not answer.endswith(end):
        chunk = port.read(port.in_waiting or 1)
        if not chunk:
            raise RuntimeError(f"no answer to {request!r}")
        answer += chunk


def p95(values: list[float]) -> float:
    return statistics.quantiles(values, n=20)[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=300)
    parser.add_argument("--faults", type=int, default=5, help="repeats of each fault")
    args = parser.parse_args()
    logging.getLogger("drivers").setLevel(logging.ERROR)  # the faults below log warnings
    rows = []
    with pty_table() as (table, transport):
        driver_status = timings(table.status, args.repeats)
        driver_line = timings(lambda: table.command("G90"), args.repeats)
        table.close()  # free the pty for the raw peer
        with serial.serial_for_url(transport.port_name, timeout=1) as port:
            port.reset_input_buffer()
            raw_status = timings(lambda: raw_round_trip(port, b"?", b">\r\n"), args.repeats)
            raw_line = timings(lambda: raw_round_trip(port, b"G90\n", b"ok\r\n"), args.repeats)
    for name, ours, peer in (
        ("'?' status", driver_status, raw_status),
        ("G90 ok", driver_line, raw_line),
    ):
        median, peer_median = statistics.median(ours), statistics.median(peer)
        rows.append((name, 1e3 * median, 1e3 * p95(ours), 1e3 * peer_median, median / peer_median))

    print(f"Round trips over a pty, {args.repeats} each (peer: raw pyserial on the same pty)")
    print(f"{'command':<12} {'median ms':>10} {'p95 ms':>8} {'peer ms':>8} {'ratio':>6}")
    for name, median, tail, peer, ratio in rows:
        print(f"{name:<12} {median:>10.3f} {tail:>8.3f} {peer:>8.3f} {ratio:>6.2f}")

    print(f"\n360 deg as 36 moves of 10 deg (real time: $110={MAX_RATE:.0f} deg/min, "
          f"$120={ACCEL:.0f} deg/s^2)")  # fmt: skip
    print(f"{'mode':<10} {'total s':>8} {'ideal s':>8} {'ratio':>6} {'overhead ms/move':>17}")
    for instant in (True, False):
        with pty_table(instant=instant, max_rate=MAX_RATE, acceleration=ACCEL) as (table, _):
            start = time.perf_counter()
            for _ in range(36):
                table.move_by(10)
            total = time.perf_counter() - start
            assert abs(table.angle - 360) < 1e-6
        ideal = 0.0 if instant else 36 * move_duration(10, MAX_RATE, ACCEL)
        ratio = f"{total / ideal:6.3f}" if ideal else f"{'-':>6}"
        mode = "instant" if instant else "real-time"
        print(f"{mode:<10} {total:>8.3f} {ideal:>8.3f} {ratio} {1e3 * (total - ideal) / 36:>17.2f}")

    print(f"\nFault mid-move to DeviceDisconnected, {args.faults} each (target <= 1 s)")
    print(f"{'fault':<26} {'median s':>9} {'max s':>7} {'<= 1 s':>7}")
    for fault, name in (("unplug", "cable pulled (pty closed)"),
                        ("silent", "link silent (port open)")):
        delays = fault_detection(fault, args.faults)
        verdict = "yes" if max(delays) <= 1.0 else "NO"
        print(f"{name:<26} {statistics.median(delays):>9.3f} {max(delays):>7.3f} {verdict:>7}")
    print_stops(args.faults)


def stop_figures(how: str, repeats: int) -> dict[str, list]:
    """Stop a move cruising at MAX_RATE ``repeats`` times with ``table.<how>()``."""
    figures = {"call_s": [], "run_deg": [], "error_deg": [], "kept": []}
    for _ in range(repeats):
        with pty_table(instant=False, max_rate=MAX_RATE, acceleration=ACCEL) as (table, tp):
            firmware = tp.firmware
            mover = threading.Thread(target=lambda: _ignore_abort(table.move_to, 3600))
            mover.start()
            cruise = (MAX_RATE / 60) ** 2 / (2 * ACCEL)
            while firmware.position_degrees() < 2 * cruise:
                time.sleep(0.002)
            at_call = firmware.position_degrees()
            start = time.perf_counter()
            getattr(table, how)()
            figures["call_s"].append(time.perf_counter() - start)
            mover.join()
            time.sleep(0.05)
            true = firmware.position_degrees()
            figures["run_deg"].append(true - at_call)
            figures["error_deg"].append(abs(table.angle - true))
            figures["kept"].append(firmware.state != "Alarm" and table.referenced)
    return figures


def _ignore_abort(move, target) -> None:
    try:
        move(target)
    except drivers.MoveAborted:
        pass


def print_stops(repeats: int) -> None:
    speed = MAX_RATE / 60
    print(f"\nStopping a move cruising at {speed:.0f} deg/s ($120={ACCEL:.0f} deg/s^2), "
          f"{repeats} each: ideal deceleration {speed / ACCEL:.3f} s over "
          f"{speed**2 / (2 * ACCEL):.1f} deg")
    print(f"{'stop':<16} {'call s':>7} {'run deg':>8} {'ideal deg':>9} {'|angle-true|':>12} "
          f"{'position kept':>13}")
    for how in ("stop", "emergency_stop"):
        f = stop_figures(how, repeats)
        ideal = speed**2 / (2 * ACCEL) if how == "stop" else 0.0
        kept = f"{sum(f['kept'])}/{repeats}"
        print(f"{how:<16} {statistics.median(f['call_s']):>7.3f} "
              f"{statistics.median(f['run_deg']):>8.2f} {ideal:>9.2f} "
              f"{max(f['error_deg']):>12.4f} {kept:>13}")


def fault_detection(fault: str, repeats: int) -> list[float]:
    """Seconds from the fault mid-move (cable pulled / link silent) to DeviceDisconnected."""
    out = []
    for _ in range(repeats):
        options = {f"{fault}_after_moves": 1, "max_rate": MAX_RATE, "acceleration": ACCEL}
        with pty_table(instant=False, **options) as (table, transport):
            try:
                table.move_to(90)
            except drivers.DeviceDisconnected:
                noticed = time.monotonic()
            else:
                raise RuntimeError(f"{fault}: the move finished, no disconnect was seen")
            firmware = transport.firmware
            out.append(noticed - (firmware.unplugged_at if fault == "unplug"
                                  else firmware.silent_at))
    return out


if __name__ == "__main__":
    main()
