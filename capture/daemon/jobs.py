"""Scan jobs: one runner per scan, at most one scan per device, state kept in the job store.

`ScanJobs` is what the HTTP routes call. It builds runners through a factory (the real
`capture.runner.ScanRunner` by default; tests inject their own), forwards every runner document
to the scan's event channel and into the store (state, progress, mesh version), and watches each
runner on a thread until it ends. An ``interrupted`` scan (the daemon died or stopped under it)
resumes from its last completed view with a new runner reading the recording, or is
re-processed from the recording alone.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import shutil
import threading
import time
import urllib.parse
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from drivers.errors import DeviceError

from .errors import Conflict, InvalidRequest, OutsideScanFolder, UnknownScan
from .events import EventChannel, EventHub
from .isolation import ProcessRunner, RunSpec, build_runner
from .refine import MeshRefiner
from .schemas import ScanRequest, check_scan_request, device_keys, is_scan_id
from .store import FINAL_STATES, JobStore, ScanRecord
from .tracking import ScanTracker

log = logging.getLogger(__name__)

SCANS_DIR = "scans"


def default_runner_factory(plan, *, camera_url, turntable_url, object, out_dir, resume_from,
                           replay=False, cluster=None):
    """The real runner, each scan in its own process (`capture.daemon.isolation`). ``replay``:
    re-run the recording in ``out_dir`` as the station, recording nothing (re-processing).
    ``cluster``: the Dask scheduler every scan's fits go to (`functools.partial` it in)."""
    return ProcessRunner(_spec(plan, camera_url, turntable_url, object, out_dir, resume_from,
                               replay, cluster))


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
    runner: Any
    devices: list[str]
    tracker: ScanTracker
    unsubscribe: Callable[[], None] | None = None
    watcher: threading.Thread | None = None


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


class ScanJobs:
    """The daemon's scans. Thread-safe; `shutdown` leaves running scans ``interrupted``."""

    def __init__(self, state_dir: str | Path, store: JobStore, hub: EventHub,
                 runner_factory: Callable[..., Any] = default_runner_factory,
                 refiner: MeshRefiner | None = None):
        self.state_dir = Path(state_dir).resolve()
        (self.state_dir / SCANS_DIR).mkdir(parents=True, exist_ok=True)
        self.store, self.hub = store, hub
        self.runner_factory = runner_factory
        self.refiner = refiner or MeshRefiner()
        self._lock = threading.RLock()
        self._live: dict[str, _Live] = {}
        self._refining: dict[str, int] = {}  # scan id -> refines under way
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
        """Device key → id of the scan holding it."""
        with self._lock:
            return dict(self._held)

    def scan_dir(self, record: ScanRecord) -> Path:
        """The scan's folder, checked to lie inside the state dir (symlinks resolved)."""
        path = (self.state_dir / record.out_dir).resolve()
        if not path.is_relative_to(self.state_dir / SCANS_DIR):
            raise OutsideScanFolder(f"scan {record.id}: folder escapes the state dir")
        return path

    def channel(self, scan_id: str) -> EventChannel:
        """The scan's event channel; for a scan this process never ran, one closed channel
        holding its current state."""
        record = self.get(scan_id)
        with self._lock:
            channel = self.hub.channel(scan_id)
            if scan_id not in self._live:  # streams of an ended scan end after its history
                if channel.last_id == 0:
                    channel.publish(_state_doc(record.state, record.reason))
                channel.close()
        return channel

    # -- commands ------------------------------------------------------------------------------
    def create(self, request: ScanRequest) -> ScanRecord:
        """Start a scan: `InvalidRequest` for a bad request, `Conflict` when a device is busy.
        A scan whose devices or folder fail at start is kept as ``failed`` with the reason."""
        try:
            plan = check_scan_request(request)
        except (ValueError, DeviceError) as exc:  # DeviceError: e.g. a backend's SDK missing
            raise InvalidRequest(str(exc)) from exc
        scan_id = uuid.uuid4().hex[:16]
        now = time.time()
        record = ScanRecord(
            id=scan_id, state="idle", request={**request.model_dump(), "plan": plan.to_dict()},
            devices=device_keys(request.camera_url, request.turntable_url),
            out_dir=f"{SCANS_DIR}/{scan_id}", created=now, updated=now,
            progress={"views_done": 0, "views_total": plan.n_views, "fraction": 0.0},
        )
        with self._lock:
            self._check_free(record.devices)
            self.store.insert(record)
            try:
                self._start(record, plan, resume_from=None)
            except InvalidRequest:
                self.store.delete(scan_id)
                raise
        return self.get(scan_id)

    def pause(self, scan_id: str) -> ScanRecord:
        """Ask the runner to pause at its next safe point (the ``paused`` document confirms)."""
        with self._lock:
            _command(self._require_live(scan_id, "pause").runner.pause, scan_id)
        return self.get(scan_id)

    def resume(self, scan_id: str) -> ScanRecord:
        """A paused scan continues; an interrupted one restarts from its last completed view."""
        with self._lock:
            record = self.get(scan_id)
            live = self._live.get(scan_id)
            if live is not None:
                _command(live.runner.resume, scan_id)
            elif record.state == "interrupted":
                self._check_free(record.devices)
                self._check_not_refining(scan_id)
                self.refiner.forget(scan_id)
                self._start(record, None, resume_from=self.scan_dir(record))
            else:
                raise Conflict(f"scan {scan_id} is {record.state}: only a paused or an "
                               "interrupted scan can be resumed")
        return self.get(scan_id)

    def cancel(self, scan_id: str) -> ScanRecord:
        """Stop after the current step; the scan ends ``interrupted`` with its views recorded."""
        with self._lock:
            _command(self._require_live(scan_id, "cancel").runner.cancel, scan_id)
        return self.get(scan_id)

    def reprocess(self, scan_id: str) -> ScanRecord:
        """Rebuild the mesh and report of an ended scan from its recording (no devices)."""
        with self._lock:
            record = self.get(scan_id)
            if scan_id in self._live or record.state not in FINAL_STATES:
                raise Conflict(f"scan {scan_id} is {record.state}: re-process it once it ended")
            from .downloads import recording_segments

            if not recording_segments(self.scan_dir(record)):
                raise Conflict(f"scan {scan_id} has no recording to re-process")
            self._check_not_refining(scan_id)
            self.refiner.forget(scan_id)  # the replay writes a new engine state
            self._start(record, None, resume_from=None, replay=True)
        return self.get(scan_id)

    def delete(self, scan_id: str) -> None:
        """Forget a scan that is not active and delete its folder."""
        with self._lock:
            record = self.get(scan_id)
            if scan_id in self._live:
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
            if scan_id in self._live or record.state not in FINAL_STATES:
                raise Conflict(f"scan {scan_id} is {record.state}: refine it once it ended")
            self._refining[scan_id] = self._refining.get(scan_id, 0) + 1
        try:
            current = record.mesh_params  # a value not given stays as the current mesh has it
            lam = current.get("lam") if lam is None else lam
            depth = current.get("depth") if depth is None else depth
            result = self.refiner.remesh(scan_id, self.scan_dir(record), lam, depth)
            with self._lock:
                version = self.get(scan_id).mesh_version + 1
                params = {"lam": result.lam, "depth": result.depth, "file": result.file}
                self.store.update(scan_id, mesh_version=version, mesh_params=params)
        finally:
            with self._lock:
                left = self._refining.pop(scan_id) - 1
                if left:
                    self._refining[scan_id] = left
        self.channel(scan_id).publish({
            "kind": "refined", "time": time.time(), "version": version, **params,
            "figures": result.figures})
        return self.get(scan_id)

    def _check_not_refining(self, scan_id: str) -> None:
        if self._refining.get(scan_id):
            raise Conflict(f"scan {scan_id} is being refined: try again when that is done")

    def shutdown(self, timeout: float = 30.0) -> None:
        """Stop every runner; their scans are left ``interrupted`` (resumable after restart)."""
        with self._lock:
            self._stopping = True
            live = list(self._live.items())
        for _, scan in live:
            with contextlib.suppress(RuntimeError):
                scan.runner.cancel()
        deadline = time.monotonic() + timeout
        for _, scan in live:
            if scan.watcher is not None:
                scan.watcher.join(max(0.0, deadline - time.monotonic()))
        self.hub.close_all()

    # -- internals -----------------------------------------------------------------------------
    def _check_free(self, devices: list[str]) -> None:
        for key in devices:
            for held, holder in self._held.items():
                if devices_overlap(key, held):
                    raise Conflict(f"device {key} is busy with scan {holder}"
                                   + ("" if key == held else f" (as {held})"))

    def _require_live(self, scan_id: str, action: str) -> _Live:
        live = self._live.get(scan_id)
        if live is None:
            raise Conflict(f"scan {scan_id} is {self.get(scan_id).state}: cannot {action} it")
        return live

    def _start(self, record: ScanRecord, plan, resume_from: Path | None,
               replay: bool = False) -> None:
        """Build and start a runner for ``record`` (lock held). ``plan`` None: the recording's."""
        if self._stopping:
            raise Conflict("the daemon is shutting down")
        request = record.request
        try:
            runner = self.runner_factory(
                plan, camera_url=request.get("camera_url"), object=request.get("object"),
                turntable_url=request.get("turntable_url"), out_dir=self.scan_dir(record),
                resume_from=resume_from, **({"replay": True} if replay else {}))
        except (ValueError, DeviceError) as exc:
            raise InvalidRequest(str(exc)) from exc
        channel = self.hub.channel(record.id)
        channel.reopen()
        tracker = ScanTracker(record.id, runner, self.scan_dir(record), self.store, channel,
                              replay)
        live = _Live(runner, [] if replay else list(record.devices), tracker)
        live.unsubscribe = runner.subscribe(tracker)
        self._live[record.id] = live
        for key in live.devices:
            self._held[key] = record.id
        state = "processing" if replay else "running"
        reason = {(True, False): "re-processing the recording",
                  (False, True): "resuming from the last completed view"}.get(
            (replay, resume_from is not None), "")
        self._set_state(record.id, state, reason)
        try:
            runner.start()
        except Exception as exc:  # the runner ends failed: nothing moved, the cause is kept
            log.warning("scan %s could not start: %s", record.id, exc)
            self._finish(record.id, live, str(exc))
            return
        live.watcher = threading.Thread(target=self._watch, args=(record.id, live),
                                        name=f"scan-{record.id}")
        live.watcher.start()

    def _watch(self, scan_id: str, live: _Live) -> None:
        """Watcher thread: wait for the runner to end, then record the outcome."""
        live.runner.wait()
        self._finish(scan_id, live, getattr(live.runner, "reason", None))

    def _finish(self, scan_id: str, live: _Live, reason: str | None) -> None:
        with self._lock:
            final = live.runner.state
            if self._stopping and final == "interrupted":
                reason = "the daemon was stopped"
            if self._live.get(scan_id) is live:
                del self._live[scan_id]
            live.unsubscribe()
            for key in live.devices:
                if self._held.get(key) == scan_id:
                    del self._held[key]
            live.tracker.finished(final)
            self._set_state(scan_id, final, reason or self.get(scan_id).reason)
        self.hub.channel(scan_id).close()

    def _set_state(self, scan_id: str, state: str, reason: str) -> None:
        self.store.update(scan_id, state=state, reason=reason)
        self.hub.channel(scan_id).publish(_state_doc(state, reason))


def _state_doc(state: str, reason: str) -> dict[str, Any]:
    """The daemon's own document: the scan's state changed."""
    return {"kind": "state", "time": time.time(), "state": state, "reason": reason}
