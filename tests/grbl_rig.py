"""Shared helpers of the GRBL driver tests: the production driver on a simulated GRBL's pty."""

import contextlib
import threading
import time

import drivers
from sim.grbl_firmware import GrblFirmware
from sim.serial_ports import PtyTransport


@contextlib.contextmanager
def rig(tmp_path, query="", **firmware_options):
    """(turntable, firmware, transport): the driver opened on ``grbl://<pty symlink>``."""
    firmware = GrblFirmware(**firmware_options)
    with PtyTransport(firmware, link=str(tmp_path / "ttyGRBL")) as transport:
        url = f"grbl://{transport.port_name}?timeout=1&poll=0.02&feed=60000{query}"
        with drivers.open_turntable(url) as table:
            yield table, firmware, transport


def run_in_thread(function, *args):
    """Start ``function(*args)``; the returned thread has ``.error`` once joined."""

    def target():
        try:
            function(*args)
        except Exception as exc:  # handed to the test
            thread.error = exc

    thread = threading.Thread(target=target)
    thread.error = None
    thread.start()
    return thread


def wait_for(predicate, timeout=3.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.005)
