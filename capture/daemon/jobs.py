"""Scan jobs: one runner per scan, at most one scan per device, state kept in the job store.

`ScanJobs` is what the HTTP routes call; none of its methods waits on a device or a process.
A new scan is ``queued`` when the daemon already runs ``max_running`` scans that hold no real
device (simulated stations, re-processing: CPU work), and refused (`TooBusy`, 429) past
``max_queued`` waiting ones; a busy device is a `Conflict` (409). A scan that may run goes to
``starting`` at once: a thread of its own builds the runner (the real `capture.runner.ScanRunner`
in a child process by default; tests inject their own), waits for it to open the devices, then
follows it until it ends, forwarding every document to the scan's event channel and into the
store (state, progress, mesh version). An ``interrupted`` scan (the daemon died or stopped under
it) resumes from its last completed view with a new runner reading the recording (or from the
start when it recorded nothing), or is re-processed from the recording alone. Reasons shown to
clients name no server path.

(Longer than most files here: the commands, the admission queue and the scans' threads keep
one set of invariants — who holds which device, what runs, what waits — under one lock.)
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import os
import shutil
import threading
import time
import urllib.parse
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from capture.plan import ScanPlan
from drivers.errors import DeviceError

from .errors import Conflict, InvalidRequest, OutsideScanFolder, TooBusy, UnknownScan
from .events import EventChannel, EventHub
from .isolation import (
    DEFAULT_OBJECT_MEMORY_BYTES,
    ProcessRunner,
    RunSpec,
    build_runner,
    folder_in_use,
)
from .policy import DevicePolicy
from .records import FINAL_STATES, ScanRecord
from .refine import MeshRefiner
from .schemas import ScanRequest, check_scan_request, device_keys, is_scan_id
from .store import JobStore
from .tracking import ScanTracker

log = logging.getLogger(__name__)

SCANS_DIR = "scans"


def default_runner_factory(plan, *, camera_url, turntable_url, object, out_dir, resume_from,
                           replay=False, cluster=None,
                           object_memory_bytes=DEFAULT_OBJECT_MEMORY_BYTES):
    """The real runner, each scan in its own process (`capture.daemon.isolation`). ``replay``:
    re-run the recording in ``out_dir`` as the station, recording nothing (re-processing);
    ``cluster``: the Dask scheduler every scan's fits go to (`functools.partial` it in);
    ``object_memory_bytes``: the child's memory budget for opening the station (loading the
    object's mesh)."""
    spec = _spec(plan, camera_url, turntable_url, object, out_dir, resume_from, replay, cluster)
    return ProcessRunner(dataclasses.replace(spec, object_memory_bytes=object_memory_bytes))


def in_process_runner_factory(plan, *, camera_url, turntable_url, object, out_dir, resume_from,
                              replay=False):
    """The real runner on threads of this process (tests, embedding in another program)."""
    return build_runner(_spec(plan, camera_url, turntable_url, object, out_dir, resume_from,
                              replay))


def _spec(plan, camera_url, turntable_url, object, out_dir, resume_from, replay,
          cluster=None) -> RunSpec:
    return RunSpec(plan, Path(out_dir), camera_url, turntable_url, object,
                   None if resume_from is None else Path(resume_from), replay,
                   logging.getLogger("capture").getEffectiveLevel(), cluster)


@dataclasses.dataclass
class _Live:
    """A scan this process runs: ``runner`` is None until its thread built it."""

    devices: list[str]
    counted: bool  # one of the ``max_running`` scans that hold no real device
    runner: Any = None
    tracker: ScanTracker | None = None
    unsubscribe: Callable[[], None] | None = None
    thread: threading.Thread | None = None
    cancel_requested: bool = False


@dataclasses.dataclass
class _Queued:
    devices: list[str]
    counted: bool
    plan: Any
    resume_from: Path | None
    replay: bool


def _command(action: Callable[[], None], scan_id: str) -> None:
    """Run a runner command; the runner's refusal (wrong state) becomes `Conflict`."""
    try:
        action()
    except RuntimeError as exc:
        raise Conflict(f"scan {scan_id}: {exc}") from exc


def devices_overlap(a: str, b: str) -> bool:
    """Whether two device keys may name one device: equal, or one is a backend's "first
    device" (``oak://``, no host or path) and the other a device of that backend."""
    if a == b:
        return True
    pa, pb = urllib.parse.urlsplit(a), urllib.parse.urlsplit(b)
    first = lambda p: not (p.netloc or p.path.strip("/") or p.query)  # noqa: E731
    return pa.scheme == pb.scheme and (first(pa) or first(pb))


def _counted(devices: list[str]) -> bool:
    """A scan with no real device (simulated station, re-processing) counts toward the
    global limit; one with a real device is limited by that device."""
    return all(key.startswith("sim://") for key in devices)


class ScanJobs:
    """The daemon's scans. Thread-safe; `shutdown` leaves running scans ``interrupted``.

    policy : what requests may name (`DevicePolicy`; default: loopback and serial devices,
        built-in objects). max_running : scans without a real device at once; max_queued :
        scans waiting for a slot before new ones are refused (`TooBusy`).
    """

    def __init__(self, state_dir: str | Path, store: JobStore, hub: EventHub,
                 runner_factory: Callable[..., Any] = default_runner_factory,
                 refiner: MeshRefiner | None = None, policy: DevicePolicy | None = None,
                 max_running: int = 2, max_queued: int = 8,
                 object_memory_bytes: int | None = None):
        if max_running < 1 or max_queued < 0:
            raise ValueError(f"max_running must be >= 1 and max_queued >= 0, got "
                             f"{max_running}, {max_queued}")
        self.state_dir = Path(state_dir).resolve()
        (self.state_dir / SCANS_DIR).mkdir(mode=0o700, parents=True, exist_ok=True)
        self.store, self.hub = store, hub
        self.runner_factory = runner_factory
        self.refiner = refiner or MeshRefiner()
        self.policy = policy or DevicePolicy()
        self.max_running, self.max_queued = max_running, max_queued
        self._factory_options = {} if object_memory_bytes is None else \
            {"object_memory_bytes": object_memory_bytes}
        self._lock = threading.RLock()
        self._live: dict[str, _Live] = {}
        self._queue: collections.OrderedDict[str, _Queued] = collections.OrderedDict()
        self._refining: dict[str, int] = {}  # scan id -> refines under way
        self._refine_locks: dict[str, threading.Lock] = {}  # scan id -> its refines' turn
        self._held: dict[str, str] = {}  # device key -> scan id
        self._stopping = False

    # -- queries -------------------------------------------------------------------------------
    def get(self, scan_id: str) -> ScanRecord:
        record = self.store.get(scan_id) if is_scan_id(scan_id) else None
        if record is None:
            raise UnknownScan(f"no scan {scan_id!r}")
        return record

    def list(self, limit: int = 100, offset: int = 0) -> list[ScanRecord]:
        return self.store.list(limit, offset)

    def busy_devices(self) -> dict[str, str]:
        """Device key → id of the scan holding it (running or queued)."""
        with self._lock:
            return dict(self._held)

    def counts(self) -> dict[str, int]:
        """Scans under way and waiting (read without the lock: for /healthz)."""
        return {"running": len(self._live), "queued": len(self._queue),
                "busy_devices": len(self._held)}

    def scan_dir(self, record: ScanRecord) -> Path:
        """The scan's folder, checked to lie inside the state dir (symlinks resolved)."""
        path = (self.state_dir / record.out_dir).resolve()
        if not path.is_relative_to(self.state_dir / SCANS_DIR):
            raise OutsideScanFolder(f"scan {record.id}: folder escapes the state dir")
        return path

    def channel(self, scan_id: str) -> EventChannel:
        """The scan's event channel; for a scan this process does not run, one closed channel
        holding its current state."""
        record = self.get(scan_id)
        with self._lock:
            channel = self.hub.channel(scan_id)
            if scan_id not in self._live and scan_id not in self._queue:
                if channel.last_id == 0:  # streams of an ended scan end after its history
                    channel.publish(_state_doc(record.state, self.clean(record.reason)))
                channel.close()
        return channel

    def clean(self, text: str) -> str:
        """``text`` (a reason, a message) without server paths, on one line."""
        text = str(text or "").splitlines()[0] if text else ""
        roots = [(str(self.state_dir / SCANS_DIR) + os.sep, ""),
                 (str(self.state_dir), "<state dir>")]
        if self.policy.object_dir is not None:
            roots.insert(0, (str(self.policy.object_dir) + os.sep, ""))
        for root, replacement in roots:
            text = text.replace(root, replacement)
        return text[:500]

    # -- commands ------------------------------------------------------------------------------
    def create(self, request: ScanRequest) -> ScanRecord:
        """Queue or start a scan (returns at once: ``queued`` or ``starting``).
        `InvalidRequest` for a bad request, `Conflict` when a device is busy, `TooBusy` when
        the queue is full. A scan whose devices or folder fail at start ends ``failed``."""
        try:
            plan, _ = check_scan_request(request, self.policy)
        except (ValueError, DeviceError) as exc:  # DeviceError: e.g. a backend's SDK missing
            raise InvalidRequest(str(exc)) from exc
        scan_id = uuid.uuid4().hex[:16]
        now = time.time()
        record = ScanRecord(
            id=scan_id, state="queued", request={**request.model_dump(), "plan": plan.to_dict()},
            devices=device_keys(request.camera_url, request.turntable_url),
            out_dir=f"{SCANS_DIR}/{scan_id}", created=now, updated=now,
            progress={"views_done": 0, "views_total": plan.n_views, "fraction": 0.0},
        )
        with self._lock:
            self._check_free(record.devices)
            self._check_room(record.devices)
            self.store.insert(record)
            self._admit(record, plan, None)
        return self.get(scan_id)

    def pause(self, scan_id: str) -> ScanRecord:
        """Ask the runner to pause at its next safe point (the ``paused`` document confirms)."""
        with self._lock:
            _command(self._require_runner(scan_id, "pause").pause, scan_id)
        return self.get(scan_id)

    def resume(self, scan_id: str) -> ScanRecord:
        """A paused scan continues; an interrupted one restarts from its last completed view
        (from the start when it recorded none)."""
        with self._lock:
            record = self.get(scan_id)
            live = self._live.get(scan_id)
            if live is not None and live.runner is not None:
                _command(live.runner.resume, scan_id)
            elif record.state == "interrupted" and live is None and scan_id not in self._queue:
                self._check_free(record.devices)
                self._check_room(record.devices)
                self._check_not_refining(scan_id)
                self._check_folder_free(record)
                self.refiner.forget(scan_id)
                folder = self.scan_dir(record)
                from .downloads import recording_segments

                if recording_segments(folder):
                    self._admit(record, None, folder)
                else:  # it never recorded a view: start it afresh
                    try:
                        plan = ScanPlan.from_dict(record.request.get("plan") or {})
                    except ValueError as exc:
                        raise Conflict(f"scan {scan_id} cannot be resumed: {exc}") from exc
                    self._admit(record, plan, None)
            else:
                raise Conflict(f"scan {scan_id} is {record.state}: only a paused or an "
                               "interrupted scan can be resumed")
        return self.get(scan_id)

    def cancel(self, scan_id: str) -> ScanRecord:
        """Stop after the current step; the scan ends ``interrupted`` with its views recorded.
        A queued scan is taken off the queue; a starting one stops once its runner exists."""
        with self._lock:
            if scan_id in self._queue:
                queued = self._queue.pop(scan_id)
                self._release(scan_id, queued.devices)
                self._set_state(scan_id, "interrupted", "cancelled by the user before it started")
                self.hub.channel(scan_id).close()
                return self.get(scan_id)
            live = self._live.get(scan_id)
            if live is None:
                raise Conflict(f"scan {scan_id} is {self.get(scan_id).state}: cannot cancel it")
            live.cancel_requested = True
            if live.runner is not None:
                _command(live.runner.cancel, scan_id)
        return self.get(scan_id)

    def reprocess(self, scan_id: str) -> ScanRecord:
        """Rebuild the mesh and report of an ended scan from its recording (no devices)."""
        with self._lock:
            record = self.get(scan_id)
            if self._active(scan_id) or record.state not in FINAL_STATES:
                raise Conflict(f"scan {scan_id} is {record.state}: re-process it once it ended")
            from .downloads import recording_segments

            if not recording_segments(self.scan_dir(record)):
                raise Conflict(f"scan {scan_id} has no recording to re-process")
            self._check_not_refining(scan_id)
            self._check_folder_free(record)
            self._check_room([])
            self.refiner.forget(scan_id)  # the replay writes a new engine state
            self._admit(record, None, None, replay=True)
        return self.get(scan_id)

    def delete(self, scan_id: str) -> None:
        """Forget a scan that is not active and delete its folder."""
        with self._lock:
            record = self.get(scan_id)
            if self._active(scan_id):
                raise Conflict(f"scan {scan_id} is {record.state}: cancel it first")
            self._check_not_refining(scan_id)
            folder = self.scan_dir(record)
            self.store.delete(scan_id)
            self.hub.drop(scan_id)
            self.refiner.forget(scan_id)
        shutil.rmtree(folder, ignore_errors=True)

    def remesh(self, scan_id: str, lam: float | None, depth: int | None) -> ScanRecord:
        """A new mesh version from the saved reconstruction with new λ / depth (no training)."""
        with self._lock:  # no reprocess, resume or delete may start while it refines
            record = self.get(scan_id)
            if self._active(scan_id) or record.state not in FINAL_STATES:
                raise Conflict(f"scan {scan_id} is {record.state}: refine it once it ended")
            self._refining[scan_id] = self._refining.get(scan_id, 0) + 1
            one_at_a_time = self._refine_locks.setdefault(scan_id, threading.Lock())
        try:
            # from the current parameters read to the event sent: else two refines crossed,
            # the earlier stored last (the current mesh went back) or read a stale λ or depth
            with one_at_a_time:
                current = self.get(scan_id).mesh_params  # a value not given stays as it is
                lam = current.get("lam") if lam is None else lam
                depth = current.get("depth") if depth is None else depth
                result = self.refiner.remesh(scan_id, self.scan_dir(record), lam, depth)
                with self._lock:
                    version = self.get(scan_id).mesh_version + 1
                    params = {"lam": result.lam, "depth": result.depth, "file": result.file}
                    self.store.update(scan_id, mesh_version=version, mesh_params=params)
                self.channel(scan_id).publish({
                    "kind": "refined", "time": time.time(), "version": version, **params,
                    "figures": result.figures})
        finally:
            with self._lock:
                left = self._refining.pop(scan_id) - 1
                if left:
                    self._refining[scan_id] = left
                else:
                    self._refine_locks.pop(scan_id, None)
        return self.get(scan_id)

    def shutdown(self, timeout: float = 30.0) -> None:
        """Stop every runner; their scans are left ``interrupted`` (resumable after restart)."""
        with self._lock:
            self._stopping = True
            for scan_id, queued in list(self._queue.items()):
                del self._queue[scan_id]
                self._release(scan_id, queued.devices)
                self._set_state(scan_id, "interrupted", "the daemon was stopped before the scan "
                                "started")
            live = list(self._live.values())
            for scan in live:
                scan.cancel_requested = True
                if scan.runner is not None:
                    with contextlib.suppress(RuntimeError):
                        scan.runner.cancel()
        deadline = time.monotonic() + timeout
        for scan in live:
            if scan.thread is not None:
                scan.thread.join(max(0.0, deadline - time.monotonic()))
        self.hub.close_all()

    # -- internals (lock held) -----------------------------------------------------------------
    def _active(self, scan_id: str) -> bool:
        return scan_id in self._live or scan_id in self._queue

    def _check_folder_free(self, record: ScanRecord) -> None:
        if folder_in_use(self.scan_dir(record)):
            raise Conflict(f"scan {record.id}: the process of its last run (of a daemon that was "
                           "killed) is still stopping: try again in a few seconds")

    def _check_not_refining(self, scan_id: str) -> None:
        if self._refining.get(scan_id):
            raise Conflict(f"scan {scan_id} is being refined: try again when that is done")

    def _check_free(self, devices: list[str]) -> None:
        for key in devices:
            for held, holder in self._held.items():
                if devices_overlap(key, held):
                    raise Conflict(f"device {key} is busy with scan {holder}"
                                   + ("" if key == held else f" (as {held})"))

    def _check_room(self, devices: list[str]) -> None:
        if self._stopping:
            raise Conflict("the daemon is shutting down")
        if _counted(devices) and self._running() >= self.max_running and \
                len(self._queue) >= self.max_queued:
            raise TooBusy(f"{self._running()} scans are running and the queue is full "
                          f"({len(self._queue)} waiting): try again later")

    def _running(self) -> int:
        return sum(live.counted for live in self._live.values())

    def _require_runner(self, scan_id: str, action: str):
        live = self._live.get(scan_id)
        if live is None or live.runner is None:
            raise Conflict(f"scan {scan_id} is {self.get(scan_id).state}: cannot {action} it")
        return live.runner

    def _admit(self, record: ScanRecord, plan, resume_from: Path | None,
               replay: bool = False) -> None:
        """Start ``record`` now if a slot is free, else queue it (its devices held)."""
        devices = [] if replay else list(record.devices)
        counted = replay or _counted(devices)
        for key in devices:
            self._held[key] = record.id
        channel = self.hub.channel(record.id)
        channel.reopen()
        if counted and (self._queue or self._running() >= self.max_running):
            self._queue[record.id] = _Queued(devices, counted, plan, resume_from, replay)
            self._set_state(record.id, "queued", f"waiting for one of {self.max_running} "
                            "scan slots")
            return
        self._launch(record.id, _Queued(devices, counted, plan, resume_from, replay))

    def _admit_queued(self) -> None:
        while self._queue and not self._stopping and self._running() < self.max_running:
            scan_id, queued = self._queue.popitem(last=False)
            self._launch(scan_id, queued)

    def _launch(self, scan_id: str, job: _Queued) -> None:
        live = _Live(job.devices, job.counted)
        self._live[scan_id] = live
        self._set_state(scan_id, "starting", "opening the devices" if not job.replay
                        else "reading the recording")
        live.thread = threading.Thread(target=self._run, args=(scan_id, live, job),
                                       name=f"scan-{scan_id}")
        live.thread.start()

    # -- the scan's own thread -----------------------------------------------------------------
    def _run(self, scan_id: str, live: _Live, job: _Queued) -> None:
        """Build and start the runner (it opens the devices: this may take the devices'
        timeouts), then follow it to its end. Never holds the lock while waiting."""
        record = self.get(scan_id)
        request = record.request
        try:
            obj = self.policy.resolve_object(request.get("object"))
            runner = self.runner_factory(
                job.plan, camera_url=request.get("camera_url"), object=obj,
                turntable_url=request.get("turntable_url"), out_dir=self.scan_dir(record),
                resume_from=job.resume_from, **({"replay": True} if job.replay else {}),
                **self._factory_options)
        except Exception as exc:  # a bad URL or object (re-checked), a missing SDK…
            self._finish(scan_id, live, "failed", f"the scan could not be set up: {exc}")
            return
        channel = self.hub.channel(scan_id)
        with self._lock:
            live.tracker = ScanTracker(scan_id, runner, self.scan_dir(record), self.store,
                                       channel, job.replay, clean=self.clean,
                                       on_start=lambda: self._started(scan_id, job))
            live.unsubscribe = runner.subscribe(live.tracker)
            live.runner = runner
            if live.cancel_requested:
                self._finish(scan_id, live, "interrupted", "cancelled by the user before it "
                             "started")
                return
        try:
            runner.start()
        except Exception as exc:  # the runner ends failed: nothing moved, the cause is kept
            log.warning("scan %s could not start: %s", scan_id, exc)
            state = runner.state if runner.state in FINAL_STATES else "failed"
            self._finish(scan_id, live, state, str(exc))
            return
        with self._lock:
            if live.cancel_requested or self._stopping:
                with contextlib.suppress(RuntimeError):
                    runner.cancel()
            else:  # a runner that sends no start document runs now too
                self._started(scan_id, job)
        runner.wait()
        self._finish(scan_id, live, runner.state, getattr(runner, "reason", None))

    def _started(self, scan_id: str, job: _Queued) -> None:
        """The runner opened its devices: ``starting`` → ``running`` (or ``processing``)."""
        with self._lock:
            if self.store.get(scan_id).state != "starting":
                return
            reason = {(True, False): "re-processing the recording",
                      (False, True): "resuming from the last completed view"}.get(
                (job.replay, job.resume_from is not None), "")
            self._set_state(scan_id, "processing" if job.replay else "running", reason)

    def _finish(self, scan_id: str, live: _Live, final: str, reason: str | None) -> None:
        with self._lock:
            if final not in FINAL_STATES:
                final = "failed"
            if self._stopping and final == "interrupted":
                reason = "the daemon was stopped"
            if self._live.get(scan_id) is live:
                del self._live[scan_id]
            if live.unsubscribe is not None:
                live.unsubscribe()
            self._release(scan_id, live.devices)
            if live.tracker is not None:
                live.tracker.finished(final)
            self._set_state(scan_id, final, reason or self.get(scan_id).reason)
            self.hub.channel(scan_id).close()
            self._admit_queued()

    def _release(self, scan_id: str, devices: list[str]) -> None:
        for key in devices:
            if self._held.get(key) == scan_id:
                del self._held[key]

    def _set_state(self, scan_id: str, state: str, reason: str) -> None:
        reason = self.clean(reason)
        self.store.update(scan_id, state=state, reason=reason)
        self.hub.channel(scan_id).publish(_state_doc(state, reason))


def _state_doc(state: str, reason: str) -> dict[str, Any]:
    """The daemon's own document: the scan's state changed."""
    return {"kind": "state", "time": time.time(), "state": state, "reason": reason}
