"""Each scan in its own process, behind the runner's interface.

A scan renders, processes and trains networks on its threads; in the daemon's process those
would share the interpreter lock with the HTTP event loop, and a status poll could wait a
second behind one long numeric call. `ProcessRunner` runs `capture.runner.ScanRunner` in a
child process instead and offers the same interface (start, pause, resume, cancel, wait,
state, reason, subscribe, documents): documents come back over a pipe as dicts, commands go
the other way. Children fork from a fork server that has already imported the capture stack,
so a scan starts in a fraction of a second; they run at a lower CPU priority (nice 10) than
the daemon, whose answers then wait for no scan. A child opens the devices and loads the
simulated camera's object itself, under a memory budget (``object_memory_bytes`` more than it
used before), so a slow device or a huge mesh costs the daemon nothing. Its files are private
(umask 077). A child outlives no daemon for long: a closed command pipe (the daemon was killed)
cancels its scan with that reason, and it exits on its own if the scan does not end soon after;
its recording keeps every completed view.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .. import LOGGERS
from ..documents import subscribe
from .tracking import as_dict, write_live_mesh

log = logging.getLogger(__name__)

TERMINAL = ("done", "failed", "interrupted")
#: scans are batch work: on a busy machine the HTTP front (status, events) is served first
SCAN_NICENESS = 10
_PRELOAD = ["capture.daemon.isolation", "capture.runner", "capture.replay"]
DEFAULT_OBJECT_MEMORY_BYTES = 2 << 30
#: how long an orphaned child (its daemon killed) may take to stop its scan before it exits
ORPHAN_GRACE_S = 60.0
ORPHANED = ("the daemon went away (killed or crashed) while the scan ran: stopped after the "
            "current step, every completed view is in the recording; resume it from the "
            "restarted daemon")


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """What one runner does: a scan (``plan`` None: the resumed recording's) or, with
    ``replay``, re-processing the recording in ``out_dir``."""

    plan: Any
    out_dir: Path
    camera_url: str | None = None
    turntable_url: str | None = None
    object: str | None = None
    resume_from: Path | None = None
    replay: bool = False
    log_level: int = logging.WARNING
    cluster: str | None = None  # Dask scheduler for the fits (`capture.executors`)
    object_memory_bytes: int | None = None


def build_runner(spec: RunSpec):
    """The `ScanRunner` for ``spec`` (not started); with ``spec.cluster`` its fits go to that
    Dask cluster (``runner.executor``, shut down by the caller)."""
    executor = None
    if spec.cluster:
        from capture.executors import make_executor

        executor = make_executor(spec.cluster)
    if spec.replay:
        from capture.replay import replay_runner

        return replay_runner(spec.out_dir, spec.out_dir, executor=executor)
    from capture.runner import ScanRunner

    return ScanRunner(spec.plan, camera_url=spec.camera_url, turntable_url=spec.turntable_url,
                      object=spec.object, out_dir=spec.out_dir, resume_from=spec.resume_from,
                      executor=executor)


def _context():
    """Fork server where there is one (fast starts, safe in a threaded parent), else spawn."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(_PRELOAD)
        return context
    return multiprocessing.get_context("spawn")


def warm_up() -> None:
    """Start the fork server now (it imports the capture stack once, in its own process)."""
    context = _context()
    if context.get_start_method() == "forkserver":
        from multiprocessing import forkserver

        forkserver.ensure_running()


class ProcessRunner:
    """A scan runner in a child process; see the module docstring."""

    def __init__(self, spec: RunSpec):
        self.spec = spec
        self.reason = ""
        self.documents: list[dict] = []
        self._state = "idle"
        self._lock = threading.Lock()
        self._subscribers: list[Callable[[dict], None]] = []
        self._ready = threading.Event()
        self._ended = threading.Event()
        self._process = None
        self._commands = None
        self._cancelled_at_start = False

    @property
    def state(self) -> str:
        return self._state

    @property
    def pid(self) -> int | None:
        """The child's process id once started."""
        return None if self._process is None else self._process.pid

    def subscribe(self, callback: Callable[[dict], None]) -> Callable[[], None]:
        return subscribe(self._lock, self._subscribers, callback)

    def start(self) -> ProcessRunner:
        """Start the child and return once its runner started; RuntimeError (one line) when the
        scan cannot start (devices, output folder), as `ScanRunner.start` raises."""
        if self._process is not None:
            raise RuntimeError(f"cannot start a scan that is {self._state}")
        context = _context()
        documents, documents_in = context.Pipe(duplex=False)
        commands_out, self._commands = context.Pipe(duplex=False)
        self._process = context.Process(target=_child, args=(documents_in, commands_out,
                                                             self.spec), name="scan")
        self._process.start()
        if self._cancelled_at_start:  # cancelled while the process was being made
            self._process.terminate()
        documents_in.close()
        commands_out.close()
        threading.Thread(target=self._read, args=(documents,), name="scan-reader",
                         daemon=True).start()
        self._ready.wait()
        if self._ended.is_set():
            raise RuntimeError(self.reason)
        return self

    def pause(self) -> None:
        """Ask the child to pause; it decides on its runner's own state (ours may be a resume
        behind: returning on "paused" here lost a pause asked just after a resume)."""
        if self._state not in ("running", "paused"):
            raise RuntimeError(f"cannot pause a scan that is {self._state}")
        self._send("pause")

    def resume(self) -> None:
        if self._state not in ("running", "paused"):
            raise RuntimeError(f"cannot resume a scan that is {self._state}")
        self._send("resume")

    def cancel(self) -> None:
        """Stop after the current step; while the child still opens the devices (a device may
        take its whole timeout to answer), stop the child at once: nothing is recorded yet."""
        if self._state in TERMINAL:
            return
        if self._state == "idle" and not self._ready.is_set():
            self._cancelled_at_start = True
            if self._process is not None and self._process.pid is not None:
                with contextlib.suppress(OSError, ValueError):
                    self._process.terminate()
            return
        self._send("cancel")

    def wait(self, timeout: float | None = None) -> str:
        self._ended.wait(timeout)
        return self._state

    def _send(self, command: str) -> None:
        try:
            self._commands.send(command)
        except (OSError, ValueError) as exc:  # the child is gone; the reader reports how
            log.warning("scan process unreachable (%s): %s not sent", exc, command)

    def _read(self, documents) -> None:
        """Reader thread: documents and state from the child until it ends or dies."""
        ended = False
        while not ended:
            try:
                message = documents.recv()
            except (EOFError, OSError):
                break
            kind, self._state = message[0], message[1]  # the child's state as it sent it
            if kind == "doc":
                self._deliver(message[2])
            elif kind == "started":
                self._ready.set()
            elif kind == "end":
                self.reason, ended = message[2], True
        self._process.join()
        if not ended and self._cancelled_at_start:
            self._state = "interrupted"
            self.reason = "cancelled by the user while the devices were opening"
        elif not ended:
            code = self._process.exitcode
            self._state = "failed"
            self.reason = f"the scan process died (exit code {code})"
        documents.close()
        self._commands.close()
        self._ended.set()
        self._ready.set()

    def _deliver(self, doc: dict) -> None:
        with self._lock:
            self.documents.append(doc)
            subscribers = list(self._subscribers)
        for callback in subscribers:
            try:
                callback(doc)
            except Exception as exc:  # one subscriber must not stop the others
                log.warning("subscriber %r failed on %s: %s", callback, doc.get("kind"), exc)


def _data_used() -> int | None:
    """Bytes of this process's data segment (Linux ``VmData``), or None where unknown."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmData:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        return None
    return None


@contextlib.contextmanager
def memory_budget(extra_bytes: int | None):
    """Allow this process ``extra_bytes`` more data than it uses now (RLIMIT_DATA), then
    restore the limit: an allocation past it raises MemoryError instead of swapping the
    station to a halt. No-op where the limit or the current use is unknown."""
    used = _data_used() if extra_bytes else None
    try:
        import resource
    except ImportError:  # not POSIX
        used = None
    if used is None:
        yield
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_DATA)
    limit = used + extra_bytes
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_DATA, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_DATA, (soft, hard))


def _out_of_memory(exc: BaseException) -> bool:
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, MemoryError):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


SCAN_LOCK = ".scan.lock"


def _hold_folder(folder: Path):
    """Lock ``folder`` for this process's life (released by the kernel when it ends), so that a
    restarted daemon does not resume a scan whose orphaned process still writes it."""
    try:
        import fcntl
    except ImportError:  # not POSIX
        return None
    folder.mkdir(parents=True, exist_ok=True)
    handle = open(folder / SCAN_LOCK, "a")  # noqa: SIM115 (held until the process ends)
    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return handle


def folder_in_use(folder: Path) -> bool:
    """Whether a scan process (of this daemon or of a killed one) still holds ``folder``."""
    try:
        import fcntl
    except ImportError:
        return False
    try:
        with open(Path(folder) / SCAN_LOCK) as handle:  # read-only: testing creates nothing
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(handle, fcntl.LOCK_UN)
    except OSError:  # no lock file (yet): nobody holds it
        return False
    return False


class Outbox:
    """The child's messages to the daemon: ``(kind, state, *payload)``, the runner's state
    read as the message goes into the pipe, under one lock. (Read before the lock, a state
    could arrive after a message another thread sent meanwhile with a newer one: a pause's
    "state: running" after the scan's own "paused", and the daemon saw a paused scan run.)"""

    def __init__(self, pipe, runner):
        self.pipe = pipe
        self.runner = runner
        self._lock = threading.Lock()

    def __call__(self, kind: str, *payload) -> None:
        with self._lock:
            self.pipe.send((kind, self.runner.state, *payload))


def _child(documents, commands, spec: RunSpec) -> None:
    """The child process: run the scan, forward its documents, obey commands."""
    os.umask(0o077)
    os.nice(SCAN_NICENESS)
    try:
        held = _hold_folder(spec.out_dir)  # noqa: F841 (kept open for the process's life)
    except BlockingIOError:
        documents.send(("end", "failed", "the scan's folder is in use by another scan process "
                        "(of a daemon that was killed): try again once it stopped"))
        return
    except OSError:  # the folder cannot be made: the runner's own check says why
        held = None  # noqa: F841
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    for name in LOGGERS:
        logging.getLogger(name).setLevel(spec.log_level)
    try:
        runner = build_runner(spec)
    except Exception as exc:
        documents.send(("end", "failed", str(exc)))
        return
    send = Outbox(documents, runner)

    def forward(doc) -> None:
        data = as_dict(doc)
        if data.get("kind") == "mesh":
            write_live_mesh(getattr(runner.engine, "mesh", None), spec.out_dir)
        with contextlib.suppress(OSError, ValueError):  # the daemon is gone: the scan stops
            send("doc", data)

    runner.subscribe(forward)
    try:
        with memory_budget(spec.object_memory_bytes if spec.object else None):
            runner.start()  # opens the devices and loads the object
    except Exception as exc:
        reason = runner.reason or str(exc)
        if _out_of_memory(exc):
            budget = (spec.object_memory_bytes or 0) / 2**20
            reason = (f"out of memory opening the station: the object needs more than the "
                      f"scan's budget of {budget:g} MiB ({reason})")
        send("end", reason)
        return
    # the daemon's cancel while it has not yet read "started" stops the child with SIGTERM,
    # meant for devices that take their timeout to open: from here on that is a cancel, which
    # ends the recording as any cancel does
    signal.signal(signal.SIGTERM, lambda *_: _cancel_once(runner))
    send("started")

    def obey() -> None:
        while True:
            try:
                command = commands.recv()
            except (EOFError, OSError):  # the daemon is gone: stop, keep what is recorded
                runner.cancel(ORPHANED)
                if runner.wait(ORPHAN_GRACE_S) not in TERMINAL:
                    log.error("scan still running %g s after its daemon went away: exiting",
                              ORPHAN_GRACE_S)
                    os._exit(1)
                return
            try:
                getattr(runner, command)()
            except RuntimeError as exc:
                log.info("%s refused: %s", command, exc)
            with contextlib.suppress(OSError, ValueError):  # the daemon is gone meanwhile
                send("state")

    threading.Thread(target=obey, name="scan-commands", daemon=True).start()
    runner.wait()
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # ended: a stop signal ends the process
    if runner.executor is not None:
        runner.executor.shutdown(wait=False, cancel_futures=True)
    with contextlib.suppress(OSError, ValueError):  # no daemon left to tell
        send("end", runner.reason)


def _cancel_once(runner) -> None:
    """A stop signal to a running scan: cancelled by the user, unless it ended or another
    cancel (the daemon's, or its going away) came first."""
    if runner.state not in TERMINAL and not runner.cancel_requested:
        runner.cancel()
