"""Each scan in its own process, behind the runner's interface.

A scan renders, processes and trains networks on its threads; in the daemon's process those
would share the interpreter lock with the HTTP event loop, and a status poll could wait a
second behind one long numeric call. `ProcessRunner` runs `capture.runner.ScanRunner` in a
child process instead and offers the same interface (start, pause, resume, cancel, wait,
state, reason, subscribe, documents): documents come back over a pipe as dicts, commands go
the other way. Children fork from a fork server that has already imported the capture stack,
so a scan starts in a fraction of a second; they run at a lower CPU priority (nice 10) than
the daemon, whose answers then wait for no scan. A child dies with the daemon (through the fork
server and PR_SET_PDEATHSIG on Linux; a closed command pipe cancels it elsewhere), as an
in-process runner would: its recording keeps every completed view.
"""

from __future__ import annotations

import ctypes
import dataclasses
import logging
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..documents import subscribe
from .tracking import as_dict, write_live_mesh

log = logging.getLogger(__name__)

TERMINAL = ("done", "failed", "interrupted")
#: scans are batch work: on a busy machine the HTTP front (status, events) is served first
SCAN_NICENESS = 10
_PRELOAD = ["capture.daemon.isolation", "capture.runner", "capture.replay"]


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
        documents_in.close()
        commands_out.close()
        threading.Thread(target=self._read, args=(documents,), name="scan-reader",
                         daemon=True).start()
        self._ready.wait()
        if self._ended.is_set():
            raise RuntimeError(self.reason)
        return self

    def pause(self) -> None:
        if self._state == "paused":
            return
        if self._state != "running":
            raise RuntimeError(f"cannot pause a scan that is {self._state}")
        self._send("pause")

    def resume(self) -> None:
        if self._state not in ("running", "paused"):
            raise RuntimeError(f"cannot resume a scan that is {self._state}")
        self._send("resume")

    def cancel(self) -> None:
        if self._state not in TERMINAL:
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
            kind = message[0]
            if kind == "doc":
                self._state = message[2]
                self._deliver(message[1])
            elif kind == "started":
                self._state = message[1]
                self._ready.set()
            elif kind == "state":
                self._state = message[1]
            elif kind == "end":
                self._state, self.reason, ended = message[1], message[2], True
        self._process.join()
        if not ended:
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


def _die_with_parent() -> None:
    if sys.platform.startswith("linux"):
        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL))


def _child(documents, commands, spec: RunSpec) -> None:
    """The child process: run the scan, forward its documents, obey commands."""
    _die_with_parent()
    os.nice(SCAN_NICENESS)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    for name in ("capture", "reconstruct", "drivers", "sim"):
        logging.getLogger(name).setLevel(spec.log_level)
    lock = threading.Lock()

    def send(message) -> None:
        with lock:
            documents.send(message)

    try:
        runner = build_runner(spec)
    except Exception as exc:
        send(("end", "failed", str(exc)))
        return

    def forward(doc) -> None:
        data = as_dict(doc)
        if data.get("kind") == "mesh":
            write_live_mesh(getattr(runner.engine, "mesh", None), spec.out_dir)
        send(("doc", data, runner.state))

    runner.subscribe(forward)
    try:
        runner.start()
    except Exception as exc:
        send(("end", runner.state, runner.reason or str(exc)))
        return
    send(("started", runner.state))

    def obey() -> None:
        while True:
            try:
                command = commands.recv()
            except (EOFError, OSError):  # the daemon is gone: stop, keep what is recorded
                runner.cancel()
                return
            try:
                getattr(runner, command)()
            except RuntimeError as exc:
                log.info("%s refused: %s", command, exc)
            send(("state", runner.state))

    threading.Thread(target=obey, name="scan-commands", daemon=True).start()
    runner.wait()
    if runner.executor is not None:
        runner.executor.shutdown(wait=False, cancel_futures=True)
    send(("end", runner.state, runner.reason))
