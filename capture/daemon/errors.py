"""The daemon's exception tree; each error is also the builtin that fits, and maps to one HTTP
status in `capture.daemon.app`."""

from __future__ import annotations


class DaemonError(Exception):
    """Base of the daemon's own failures."""


class UnknownScan(DaemonError, LookupError):
    """No scan with that id (404)."""


class Conflict(DaemonError, RuntimeError):
    """The scan or its devices are in the wrong state for the request (409): a device busy with
    another scan, pausing a finished scan, deleting a running one…"""


class Unavailable(DaemonError, FileNotFoundError):
    """A download that does not exist (yet) for this scan (404): no mesh before the first one."""


class InvalidRequest(DaemonError, ValueError):
    """A request that cannot run as given (422): a bad plan, device URL or object."""


class OutsideScanFolder(DaemonError, PermissionError):
    """A file name that would lead out of the scan's folder (answered as 404)."""


class TooBusy(DaemonError, RuntimeError):
    """The daemon runs and queues as many scans as it may: try again later (429)."""

    retry_after_s = 10
