"""The life cycle of a scan: an explicit state table, requests, subscribers and documents.

States (bluesky's run engine): idle → running ⇄ paused → stopping → done / failed / interrupted.
`RunLifecycle` owns the state (every change goes through `TRANSITIONS`; anything else raises
`InvalidTransition`), the pause / resume / cancel requests the worker honours at its
checkpoints, and the document stream: each document is numbered, kept in ``documents`` and sent
to the recorder first (a recording that fails stops the scan), then to the run's own writers
(``scan.json``: `capture.report.ScanReport`) and then to every subscriber (a failing subscriber
is logged and skipped).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time

from .documents import Document, PausedDocument, ResumedDocument, subscribe
from .outputs import OutputError

log = logging.getLogger("capture.runner")

TERMINAL = ("done", "failed", "interrupted")
TRANSITIONS = {
    ("idle", "start"): "running",
    ("idle", "cancel"): "interrupted",
    ("idle", "fail"): "failed",
    ("running", "pause"): "paused",
    ("running", "stop"): "stopping",
    ("running", "fail"): "failed",
    ("paused", "resume"): "running",
    ("paused", "stop"): "stopping",
    ("paused", "fail"): "failed",
    ("stopping", "done"): "done",
    ("stopping", "interrupt"): "interrupted",
    ("stopping", "fail"): "failed",
}


class CaptureError(RuntimeError):
    """A scan that cannot start or go on (the message names the cause in one line)."""


class InvalidTransition(CaptureError):
    """A request the runner's current state does not allow (e.g. resume() while running)."""


class Cancelled(Exception):
    """Raised inside the worker when a cancel request reaches a checkpoint."""


class RunLifecycle:
    """State, requests and documents of one run; the worker is the subclass's."""

    def __init__(self):
        self.documents: list[Document] = []
        self._state = "idle"
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._subscribers: list = []
        self._recorder = None
        self._writers: list = []  # after the recorder, before the subscribers
        self._pause_requested = threading.Event()
        self._resume_requested = threading.Event()
        self._cancel_requested = threading.Event()
        self.cancel_reason = "cancelled by the user"

    # -- state ---------------------------------------------------------------------------------
    @property
    def state(self) -> str:
        return self._state

    def _transition(self, event: str) -> str:
        with self._changed:
            new = TRANSITIONS.get((self._state, event))
            if new is None:
                raise InvalidTransition(f"cannot {event} a scan that is {self._state}")
            log.debug("scan: %s --%s--> %s", self._state, event, new)
            self._state = new
            self._changed.notify_all()
            return new

    def wait_for_state(self, *states: str, timeout: float | None = None) -> str:
        with self._changed:
            self._changed.wait_for(lambda: self._state in states + TERMINAL, timeout)
            return self._state

    # -- subscribers and documents -------------------------------------------------------------
    def subscribe(self, callback):
        """Call ``callback(document)`` for every later document; returns an unsubscribe()."""
        return subscribe(self._lock, self._subscribers, callback)

    def _emit(self, cls, **fields) -> Document:
        with self._lock:
            document = cls(seq=len(self.documents), time=time.time(), **fields)
            self.documents.append(document)
            subscribers = [*self._writers, *self._subscribers]
            if self._recorder is not None:
                subscribers.insert(0, self._recorder)
            for callback in subscribers:
                try:
                    callback(document)
                except Exception as exc:
                    if callback is self._recorder:  # cannot record: stop the scan
                        self._recorder = None
                        raise OutputError(f"recording to {callback.path} failed: {exc}") from exc
                    log.warning("subscriber %r failed on %s: %s", callback, cls.kind, exc)
        return document

    @property
    def cancel_requested(self) -> bool:
        """Whether a cancel was asked (the scan stops at its next checkpoint)."""
        return self._cancel_requested.is_set()

    # -- requests ---------------------------------------------------------------------------------
    # No lock orders the requests and the checkpoint (a subscriber may ask for one while a
    # document is emitted under the documents' lock, and the daemon holds its own while it
    # asks): the checkpoint clears the resume flag before it looks again whether it was
    # cancelled or the pause withdrawn, and a request sets its flags in the order that makes
    # every interleaving end as asked (a request lost there left the scan paused for good).
    def pause(self) -> None:
        """Ask the scan to pause at its next safe point (between frames or views). Asked while
        paused, it holds for after a resume on its way (else `resume(); pause()` ran on)."""
        if self._state not in ("running", "paused"):
            raise InvalidTransition(f"cannot pause a scan that is {self._state}")
        self._pause_requested.set()

    def resume(self) -> None:
        """Resume a paused scan (after a lost device: try to reconnect it again)."""
        if self._state not in ("running", "paused"):
            raise InvalidTransition(f"cannot resume a scan that is {self._state}")
        self._pause_requested.clear()  # running: the pause withdrawn, or met at once if taken
        self._resume_requested.set()

    def cancel(self, reason: str = "cancelled by the user") -> None:
        """Stop after the current step; what was recorded stays (state ``interrupted``, with
        ``reason``: who or what cancelled)."""
        self.cancel_reason = reason
        if self._state == "idle":
            with contextlib.suppress(InvalidTransition):  # else it started meanwhile
                self._transition("cancel")
                self.reason = "cancelled before it started"
                return
        self._cancel_requested.set()
        self._resume_requested.set()

    # -- checkpoints (in the worker) ------------------------------------------------------------
    def _checkpoint(self, index: int) -> None:
        if self._cancel_requested.is_set():
            raise Cancelled
        if not self._pause_requested.is_set():
            return
        self._resume_requested.clear()  # a resume or cancel from here on ends the pause
        if self._cancel_requested.is_set():  # one before it: looked at again
            raise Cancelled
        if not self._pause_requested.is_set():  # withdrawn by a resume before it
            return
        self._pause_requested.clear()
        self._transition("pause")
        self._emit(PausedDocument, reason="user", message="paused by the user",
                   view_index=index)
        self._block_until_resumed()
        self._transition("resume")
        self._emit(ResumedDocument, message=f"resumed by the user at view {index + 1}",
                   view_index=index)

    def _block_until_resumed(self) -> None:
        self._resume_requested.wait()
        self._resume_requested.clear()
        if self._cancel_requested.is_set():
            raise Cancelled
