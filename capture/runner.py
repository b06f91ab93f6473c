"""The scan runner: executes a `ScanPlan` on a station (states: `capture.lifecycle`).

`start()` checks the output folder (writable, room for the recording) and opens the station
BEFORE anything moves, then a worker thread runs the views: move, settle, grab, combine per
pixel, record (the view's chunk is synced), process, feed the engine, emit documents. A lost
device (`DeviceDisconnected`, `DeviceTimeout`) pauses the scan with a message, reconnects with
backoff for ``plan.reconnect_timeout_s``, then resumes at the view it was on; views already
recorded are never redone or lost. `pause()` takes effect between views or frames.

Recorded views take one path: a resumed scan feeds its recorded views through the same per-view
step as captured ones, without announcing them again (their documents are in the recording it
continues); a replay (``replay=``, `capture.replay.replay_runner`) feeds every view of a
recording through it and announces them, with no device. ``scan.json`` is written by a document
subscriber (`capture.report.ScanReport`).
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
import uuid
from pathlib import Path

from drivers.errors import DeviceDisconnected, DeviceTimeout

from .combine import combine_depths
from .documents import (
    ErrorDocument,
    MeshDocument,
    PausedDocument,
    ProgressDocument,
    ResumedDocument,
    StartDocument,
    StopDocument,
    ViewDocument,
)
from .lifecycle import (  # noqa: F401  (re-exported: the runner's public names)
    TERMINAL,
    TRANSITIONS,
    Cancelled,
    CaptureError,
    InvalidTransition,
    RunLifecycle,
)
from .live.engine import IncrementalEngine
from .outputs import ScanOutputs
from .plan import ScanPlan
from .processing import ViewProcessor
from .recording import Recording, RecordingWriter, next_segment, read_recording, segment_paths
from .report import ScanReport
from .station import Station, open_station, recorded_station

log = logging.getLogger(__name__)


class DeviceLost(CaptureError):
    """A device call failed with a disconnect or a timeout (``device``: which one)."""

    def __init__(self, device: str, cause: Exception):
        super().__init__(f"{device} lost: {cause}")
        self.device, self.cause = device, cause


class ScanRunner(RunLifecycle):
    """Run one scan (or resume one). See the module docstring for the life cycle.

    plan : `ScanPlan` (None: the resumed recording's, else the default 36-view plan).
    camera_url, turntable_url, object : the station (`capture.station.open_station`); or
        ``station``: an open `Station`, owned and closed.
    out_dir : folder for recording.mcap, mesh.ply, scan.json.
    resume_from : a scan folder whose recording is replayed into the engine; the remaining
        views are captured into a new segment (``recording-2.mcap``…) in ``out_dir``.
    replay : a `Recording` whose views are the scan's (no device; `capture.replay`).
    record : write the MCAP recording (replays do not).
    calibration : a `Calibration` or calibration file (default: the simulator's truth, or the
        resumed recording's).  seed : simulated camera noise seed.
    workers : processes for the engine's patch fits (the mesh does not depend on it).
    executor : where the fits run instead (`capture.executors`; the caller shuts it down).
    schedule : the engine's update schedule (`IncrementalEngine`; replays pass the live one).
    """

    def __init__(self, plan: ScanPlan | None = None, camera_url=None, turntable_url=None,
                 object=None, out_dir="scan", resume_from=None, *, station: Station | None = None,
                 calibration=None, record: bool = True, seed: int = 0, workers: int = 1,
                 schedule=None, replay: Recording | None = None, executor=None):
        self.out_dir = Path(resume_from if resume_from is not None and out_dir == "scan"
                            else out_dir)
        self.resume_from = None if resume_from is None else Path(resume_from)
        self._plan = plan
        self._station_args = (camera_url, turntable_url, object, calibration, seed)
        self.station = station
        self.replay = replay
        self.record = record
        self.workers = workers
        self.executor = executor
        self.schedule = schedule
        self.scan_id = uuid.uuid4().hex
        super().__init__()
        self.engine: IncrementalEngine | None = None
        self.plan: ScanPlan | None = plan
        self._thread: threading.Thread | None = None
        self._recorder: RecordingWriter | None = None
        self._started = 0.0
        self.reason = ""
        self.image_shape: tuple[int, int] | None = None
        self.error: BaseException | None = None
        self._said_empty = False  # a view without points was reported
        self._limits: collections.Counter = collections.Counter()  # views reaching each limit

    @classmethod
    def resume_recording(cls, out_dir, **kwargs) -> ScanRunner:
        """A runner (not started) continuing the interrupted scan in ``out_dir``."""
        return cls(resume_from=out_dir, out_dir=out_dir, **kwargs)

    def wait(self, timeout: float | None = None) -> str:
        """Block until the scan is done, failed or interrupted (or ``timeout`` s); the state."""
        with self._changed:
            self._changed.wait_for(lambda: self._state in TERMINAL, timeout)
        if self._thread is not None and self._state in TERMINAL:
            self._thread.join()
        return self._state

    def start(self) -> ScanRunner:
        """Check the output, open the station, then run the views on a worker thread.

        Raises `CaptureError` (and ends ``failed``) when the scan cannot start; nothing has
        moved then."""
        self._transition("start")
        self._started = time.monotonic()
        try:
            self._prepare()
        except Exception as exc:
            self._fail_early(exc)
            raise CaptureError(str(exc)) from exc
        except BaseException as exc:  # Ctrl-C while the devices open: closed, then it goes on
            self._fail_early(RuntimeError(f"interrupted while starting ({type(exc).__name__})"))
            raise  # (its devices' threads left open hung the process's exit for good)
        self._thread = threading.Thread(target=self._main, name="scan-runner", daemon=True)
        self._thread.start()
        return self

    # -- preparation (before anything moves) ----------------------------------------------------
    def _prepare(self) -> None:
        camera_url, turntable_url, object, calibration, seed = self._station_args
        recorded = []
        if self.replay is not None:
            recorded = self.replay.views
            if self.station is None:
                self.station = recorded_station(self.replay)
        elif self.resume_from is not None:
            recording = read_recording(self.resume_from)
            _check_same_views(self._plan, recording.plan, self.resume_from)
            self._plan = self._plan or recording.plan
            calibration = calibration or recording.calibration
            if self.station is None and camera_url is None and turntable_url is None:
                camera_url = recording.station.get("camera")
                turntable_url = recording.station.get("turntable")
            recorded = recording.views
            self.scan_id = recording.scan_id or self.scan_id  # one scan, several segments
        elif self.record and self.out_dir.is_dir() and segment_paths(self.out_dir):
            raise CaptureError(f"{self.out_dir} already holds a scan recording: resume it "
                               "(--resume) or choose another output folder")
        elif self.out_dir.is_dir() and (held := ScanOutputs(self.out_dir).held()):
            raise CaptureError(f"{self.out_dir} already holds {', '.join(held)}, which a new "
                               "scan would replace: choose another output folder")
        self.plan = (self._plan or ScanPlan()).validate()
        self.outputs = ScanOutputs(self.out_dir)
        self.outputs.check_writable()
        if self.station is None:
            self.station = open_station(camera_url, turntable_url, object, calibration, seed)
        self.outputs.check_space(self.plan, self.station.intrinsics, self.record)
        done = {v.index for v in recorded}
        self._recorded = recorded
        self._pending = [] if self.replay is not None else \
            [i for i in range(self.plan.n_views) if i not in done]
        self._views_done = 0 if self.replay is not None else len(recorded)
        self.processor = ViewProcessor(
            self.station.calibration, self.plan.volume, voxel_mm=self.plan.voxel_mm,
            outlier_neighbors=self.plan.outlier_neighbors, outlier_std=self.plan.outlier_std)
        if self.plan.reconstruction is not None:
            self.engine = IncrementalEngine(self.plan.reconstruction, on_mesh=self._on_mesh,
                                            workers=self.workers, total_views=self.plan.n_views,
                                            schedule=self.schedule, executor=self.executor)
        unannounced = recorded and self.replay is None
        self._writers.append(ScanReport(self.outputs, self.engine, started=self._started,
                                        image_shape=recorded[-1].frames[0].shape
                                        if unannounced else None))
        if self.record:
            self.segment, path = next_segment(self.out_dir)
            self._recorder = RecordingWriter(
                path, self.plan, self.station.calibration, self.station.describe(),
                self.scan_id, self.segment).open()
        else:
            self.segment = 0

    def _fail_early(self, exc: Exception) -> None:
        self.error, self.reason = exc, str(exc)
        log.debug("scan cannot start: %s", exc)  # (raised: the caller says it, once)
        self._emit(ErrorDocument, error=type(exc).__name__, message=str(exc))
        self._emit(StopDocument, state="failed", reason=str(exc), views_done=0,
                   views_total=self._plan.n_views if self._plan else 0, files={})
        self._close()
        self._transition("fail")

    # -- the worker ----------------------------------------------------------------------------
    def _main(self) -> None:
        try:
            self._emit(StartDocument, scan_id=self.scan_id, plan=self.plan.to_dict(),
                       calibration=json.loads(self.station.calibration.to_json()),
                       station=self.station.describe(), segment=self.segment,
                       resumed_views=0 if self.replay is not None else len(self._recorded))
            self._feed_recorded()
            for index in self._pending:
                measured, frames = self._capture_with_recovery(index)
                self._complete_view(index, measured, [f.depth for f in frames],
                                    [f.timestamp for f in frames])
            self._transition("stop")
            self._finish()
            self._end("done", f"all {self.plan.n_views} views captured")
        except Cancelled:
            if self._state != "stopping":
                self._transition("stop")
            self._end("interrupt", self.cancel_reason)
        except Exception as exc:
            self.error = exc
            log.error("scan failed: %s", exc)
            try:
                self._emit(ErrorDocument, error=type(exc).__name__, message=str(exc))
            finally:
                self._end("fail", str(exc))
        finally:
            self._close()

    def _feed_recorded(self) -> None:
        """The recorded views, in their order, through the per-view step: announced in a
        replay (which may be paused or cancelled between them), silently in a resume."""
        announce = self.replay is not None
        for index, view in enumerate(self._recorded):
            if announce:
                self._checkpoint(index)
            frames = view.frames[: self.plan.frames_per_view] if announce else view.frames
            self._complete_view(index, view.measured_angle_deg, frames,
                                view.timestamps[: len(frames)], announce=announce)
        if self._recorded and not announce:
            log.info("resumed %d recorded views; %d to capture", len(self._recorded),
                     len(self._pending))

    def _process(self, combined, angle_deg: float) -> tuple[int, tuple[str, ...]]:
        """Process and merge one view; (its points, the limits of view it reaches)."""
        points = self.processor.process(combined, angle_deg)
        if self.engine is not None:
            self.engine.add_view(points)
        limits = self.processor.limits(combined, angle_deg, points)
        self._limits.update(limits)
        return len(points), limits

    def _device(self, name: str, call, *args):
        try:
            return call(*args)
        except (DeviceDisconnected, DeviceTimeout) as exc:
            raise DeviceLost(name, exc) from exc

    def _capture_view(self, index: int):
        """Move, settle, read the angle back, grab the frames: (measured angle, frames)."""
        table, camera = self.station.turntable, self.station.camera
        self._checkpoint(index)
        self._device("turntable", table.move_to, self.plan.angles[index])
        if self.plan.settle_s and self._cancel_requested.wait(self.plan.settle_s):
            raise Cancelled
        measured = float(self._device("turntable", lambda: table.angle))
        frames = []
        for _ in range(self.plan.frames_per_view):
            self._checkpoint(index)
            frames.append(self._device("camera", camera.grab))
        return measured, frames

    def _capture_with_recovery(self, index: int):
        while True:
            try:
                return self._capture_view(index)
            except DeviceLost as lost:
                self._recover(lost, index)

    def _recover(self, lost: DeviceLost, index: int) -> None:
        """Paused until ``lost.device`` is back (retries with backoff); then resume the view."""
        n = self.plan.n_views
        message = (f"{lost.device} disconnected at view {index + 1}/{n} ({lost.cause}); "
                   f"reconnecting")
        log.warning("scan paused: %s", message)
        self._resume_requested.clear()
        self._transition("pause")
        self._emit(PausedDocument, reason="device", message=message, view_index=index)
        limit = self.plan.reconnect_timeout_s
        while not self._reconnect(lost.device, limit):
            if self.plan.on_device_lost == "fail":
                raise CaptureError(f"{lost.device} did not come back within {limit:g} s "
                                   f"({lost.cause}); {self._views_done} views are recorded")
            log.warning("%s still gone after %g s: the scan stays paused (resume() retries, "
                        "cancel() stops; recorded views are kept)", lost.device, limit)
            self._block_until_resumed()
        log.info("%s reconnected: resuming at view %d/%d", lost.device, index + 1, n)
        self._transition("resume")
        self._emit(ResumedDocument, message=f"{lost.device} reconnected; resuming at view "
                   f"{index + 1}/{n}", view_index=index)

    def _reconnect(self, device: str, limit: float) -> bool:
        deadline, delay = time.monotonic() + limit, 0.05
        while True:
            if self._cancel_requested.is_set():
                raise Cancelled
            try:
                self.station.reconnect(device)
                return True
            except (OSError, ValueError) as exc:  # device errors are OSError / ValueError too
                log.info("reconnecting %s failed: %s", device, exc)
            if time.monotonic() + delay > deadline:
                return False
            if self._cancel_requested.wait(delay):
                raise Cancelled
            delay = min(2 * delay, 2.0)

    def _complete_view(self, index: int, measured: float, depths, timestamps,
                       announce: bool = True) -> None:
        """Combine, (announce,) process and merge one view: (H, W) depth frames, mm."""
        self.image_shape = depths[0].shape
        combined = combine_depths(depths, self.plan.combine)
        if not announce:
            self._process(combined, measured)
            return
        self._emit(ViewDocument, index=index, angle_deg=self.plan.angles[index],
                   measured_angle_deg=measured, n_frames=len(depths),
                   valid_pixels=int((combined > 0).sum()),
                   timestamps=tuple(float(t) for t in timestamps), frames=tuple(depths))
        self._views_done += 1
        n_points, limits = self._process(combined, measured)
        if n_points == 0 and not self._said_empty:  # once: the camera sees nothing to scan
            self._said_empty = True
            log.warning("view %d/%d: no points in the working volume (%s): is the object on "
                        "the plate and inside it?", index + 1, self.plan.n_views,
                        self.plan.volume.describe())
        self._emit(ProgressDocument, views_done=self._views_done, views_total=self.plan.n_views,
                   view_points=n_points, view_limits=limits,
                   cloud_points=len(self.engine.cloud) if self.engine else 0,
                   elapsed_s=time.monotonic() - self._started)

    def _on_mesh(self, engine: IncrementalEngine, figures: dict) -> None:
        with self._lock:  # a fit running at a cancel or failure may end after the stop document
            if self.documents and self.documents[-1].kind == "stop":
                log.debug("mesh v%d ended after the scan stopped: not published (scan.json and "
                         "the scan's files are the stop's)", figures["version"])
                return
            self._emit(MeshDocument, version=figures["version"], views=figures["views"],
                       final=bool(figures.get("final")), figures=figures)

    # -- the end -------------------------------------------------------------------------------
    def _finish(self) -> None:
        self._say_limits()
        if self.engine is None:
            return
        mesh = self.engine.finish()
        if mesh is None:
            seen = len(self.engine.cloud.points(self.engine.params.min_views))
            raise CaptureError(
                f"no mesh: {seen} points in the working volume ({self.plan.volume.describe()}) "
                f"were seen in {self.engine.params.min_views} views or more: is the object on "
                f"the plate and inside it?")
        self.outputs.write_mesh(mesh)
        self.outputs.write_cloud(self.engine.fitted_points)
        self.outputs.write_engine(self.engine)

    def _say_limits(self) -> None:
        """One warning per limit of view the object reached (`ViewProcessor.limits`)."""
        volume, views = self.plan.volume, self.plan.n_views
        where = {"image edge": "the edge of the camera's image",
                 "wall": f"the working volume's side ({volume.radius_mm:g} mm from the axis)",
                 "roof": f"the working volume's top ({volume.z_max_mm:g} mm above the plate)"}
        for limit, count in self._limits.items():
            log.warning("the object reaches %s in %d of %d views: what lies beyond is not "
                        "scanned", where[limit], count, views)

    def _end(self, event: str, reason: str) -> None:
        """Report, emit the stop document and reach the final state, whatever fails on the way
        (the recording already holds every completed view)."""
        state = TRANSITIONS[(self._state, event)]
        self.reason = reason
        try:
            if self.engine is not None and state != "done":
                self.engine.cancel()
            files = {}
            try:  # scan.json itself is written by `ScanReport` on the stop document
                files = self.outputs.final_files()
            except Exception as exc:
                log.error("could not list the scan's files: %s", exc)
            self._emit(StopDocument, state=state, reason=reason, views_done=self._views_done,
                       views_total=self.plan.n_views, files=files)
        except Exception as exc:
            log.error("ending the scan: %s", exc)
        finally:
            self._transition(event)

    def _close(self) -> None:
        # a cancelled or failed scan's fit under way is not waited for: its mesh would follow
        # the stop (not published), and the devices and the end would wait seconds for it
        done = self._state == "done"
        for closer in (self.engine and (lambda: self.engine.close(wait=done)),
                       self._recorder and self._recorder.close,
                       self.station and self.station.close):
            if closer:
                try:
                    closer()
                except Exception as exc:
                    log.warning("closing after the scan failed: %s", exc)


def _check_same_views(plan: ScanPlan | None, recorded: ScanPlan, where) -> None:
    """`CaptureError` unless a resumed scan's ``plan`` (None: the recorded one) has the
    ``recorded`` plan's views: its views are taken by index (a resume with 8 views for 4
    recorded captured 90 deg twice and 45 deg never, and ended done)."""
    if plan is None:
        return
    same = (len(plan.angles) == len(recorded.angles)
            and all(abs(a - b) <= 1e-9 for a, b in zip(plan.angles, recorded.angles, strict=True))
            and plan.frames_per_view == recorded.frames_per_view)
    if not same:
        raise CaptureError(f"{where}: a resumed scan keeps its recorded views ({recorded.n_views} "
                           f"views, {recorded.frames_per_view} frames each), and this plan's "
                           f"differ ({plan.n_views} views, {plan.frames_per_view} frames each): "
                           "resume without a plan, or start a new scan")
