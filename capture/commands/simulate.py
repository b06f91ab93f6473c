"""`scanstation simulate-turntable`: the simulated GRBL 1.1h on a pseudo-terminal, for another
process (a `scanstation scan --turntable grbl:///dev/pts/N`, a GRBL sender, a serial terminal)
to open exactly as it would open a USB adapter. Runs until Ctrl-C or SIGTERM."""

from __future__ import annotations

import logging

log = logging.getLogger("capture.cli")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate-turntable",
        help="serve the simulated GRBL turntable on a pseudo-terminal (/dev/pts/N)")
    parser.add_argument("--link", metavar="PATH", help="also a stable symlink to the pty")
    parser.add_argument("--instant", action="store_true",
                        help="moves complete at once (default: real time)")
    parser.add_argument("--max-rate", type=float, default=3600.0, metavar="DEG_PER_MIN",
                        help="$110, degrees/min (3600)")
    parser.add_argument("--accel", type=float, default=360.0, metavar="DEG_PER_S2",
                        help="$120, degrees/s² (360)")
    parser.set_defaults(run=run)


def run(args) -> int:
    import signal
    import threading

    from sim.grbl_firmware import GrblFirmware
    from sim.serial_ports import PtyTransport

    if not (0 < args.max_rate < float("inf") and 0 < args.accel < float("inf")):  # (NaN too)
        raise ValueError("--max-rate and --accel must be finite numbers > 0")
    firmware = GrblFirmware(instant=args.instant, max_rate=args.max_rate,
                            acceleration=args.accel)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with PtyTransport(firmware, link=args.link) as transport:
        print(f"simulated GRBL 1.1h on {transport.port_name}: open grbl://{transport.port_name}",
              flush=True)
        try:
            stop.wait()
        except KeyboardInterrupt:
            pass
    log.info("simulator stopped")
    return 0
