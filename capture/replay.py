"""Replay: a recording acts as the station, and the same runner re-runs the scan from it.

`ReplayTurntable` and `ReplayCamera` implement the drivers' interfaces over a `Recording`: each
``move_to`` steps to the next recorded view (its angle must match), the table then reads back
the recorded angle and the camera hands out that view's recorded frames in order. The runner,
processing and engine are the live scan's own, and the engine follows the live scan's recorded
update schedule, so with the same plan and seed the replay builds the same mesh.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from drivers.base import DepthCamera, Frame, Turntable
from drivers.errors import DeviceError

from .plan import ScanPlan
from .recording import Recording, RecordingError, read_recording
from .station import Station

log = logging.getLogger(__name__)


class _Cursor:
    """Which recorded view the replayed station is at (shared by its camera and table)."""

    def __init__(self, recording: Recording):
        self.recording = recording
        self.view = -1
        self.frame = 0


class _ReplayDevice:
    """What both replay devices share: built on a cursor, never from a URL, nothing to open."""

    schemes = ("replay",)
    kind = ""

    def __init__(self, cursor: _Cursor):
        super().__init__(f"replay://{self.kind}")
        self._cursor = cursor

    @classmethod
    def from_url(cls, url: str, **options):
        raise DeviceError("replay devices come from a recording (capture.replay.replay_station)")

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass


class ReplayTurntable(_ReplayDevice, Turntable):
    """A turntable that steps through the recorded views."""

    kind = "turntable"

    def home(self) -> None:
        self._cursor.view, self._cursor.frame = -1, 0

    def move_to(self, degrees: float) -> None:
        cursor = self._cursor
        views = cursor.recording.views
        if cursor.view + 1 >= len(views):
            raise DeviceError(f"replay: no recorded view left for a move to {degrees:g}°")
        expected = views[cursor.view + 1].angle_deg
        if not np.isclose(expected, degrees, atol=1e-6):
            raise DeviceError(f"replay: the recording's next view is at {expected:g}°, "
                              f"not {degrees:g}°")
        cursor.view, cursor.frame = cursor.view + 1, 0

    @property
    def angle(self) -> float:
        cursor = self._cursor
        return cursor.recording.views[cursor.view].measured_angle_deg if cursor.view >= 0 else 0.0

    def wait_until_still(self, timeout: float | None = None) -> None:
        pass

    def stop(self) -> None:
        pass


class ReplayCamera(_ReplayDevice, DepthCamera):
    """A camera that returns the current recorded view's frames, in order."""

    kind = "camera"

    @property
    def intrinsics(self) -> np.ndarray:
        return self._cursor.recording.calibration.intrinsics.copy()

    def grab(self, timeout: float | None = None) -> Frame:
        cursor = self._cursor
        if cursor.view < 0:
            raise DeviceError("replay: grab before the first move")
        view = cursor.recording.views[cursor.view]
        if cursor.frame >= len(view.frames):
            raise DeviceError(f"replay: view {view.index} has only {len(view.frames)} frames")
        j = cursor.frame
        cursor.frame += 1
        return Frame(depth=view.frames[j], timestamp=view.timestamps[j], sequence=j)


def replay_station(recording: Recording) -> Station:
    """A `Station` whose devices replay ``recording`` (the recorded calibration with them).
    The camera URL stays the recorded one, so a simulated object's truth is still found."""
    cursor = _Cursor(recording)
    return Station(
        camera=ReplayCamera(cursor).open(),
        turntable=ReplayTurntable(cursor).open(),
        calibration=recording.calibration,
        camera_url=recording.station.get("camera", "replay://camera"),
        turntable_url="replay://turntable",
    )


def replay_plan(recording: Recording, **reconstruction) -> ScanPlan:
    """The recorded plan restricted to the recorded views (in their order), no settling; and
    ``reconstruction`` parameters overridden (e.g. ``lam=2.0``)."""
    if not recording.views:
        raise RecordingError(f"{recording.segments[0]}: the recording holds no complete view")
    plan = recording.plan
    params = plan.reconstruction
    if params is not None and reconstruction:
        params = dataclasses.replace(params, **reconstruction)
    frames = min(len(v.frames) for v in recording.views)
    return dataclasses.replace(plan, angles=tuple(recording.angles), settle_s=0.0,
                               frames_per_view=frames, reconstruction=params).validate()


def replay_runner(source, out_dir, workers: int = 1, schedule="recorded", executor=None,
                  **reconstruction):
    """A `ScanRunner` (not started) re-running the recording at ``source`` (a file or a scan
    folder) into ``out_dir``, without recording again; ``reconstruction`` overrides parameters
    (e.g. ``lam=2.0``); ``workers``, ``executor`` as in `ScanRunner`; ``schedule``: the
    engine's updates, "recorded" (the live scan's: same mesh), or a list of view counts ([] :
    only the final)."""
    from .runner import ScanRunner

    recording = source if isinstance(source, Recording) else read_recording(source)
    if not recording.complete:
        log.warning("%s was cut short: replaying the %d complete views it holds",
                    recording.segments[-1], len(recording.views))
    plan = replay_plan(recording, **reconstruction)
    return ScanRunner(plan, out_dir=out_dir, station=replay_station(recording), record=False,
                      workers=workers, executor=executor,
                      schedule=recorded_schedule(recording) if schedule == "recorded" else schedule)


def recorded_schedule(recording: Recording) -> list[int] | None:
    """The live engine's update schedule (view counts), from the last recorded mesh document;
    None when the recording has no mesh (then the replay's engine schedules its own)."""
    meshes = [d for d in recording.documents if d.get("kind") == "mesh"]
    if not meshes or "schedule" not in meshes[-1].get("figures", {}):
        return None
    return list(meshes[-1]["figures"]["schedule"])
