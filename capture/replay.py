"""Replay: the same runner re-runs a scan from its recording, with no device.

`replay_runner` hands the recording to a `ScanRunner` (``replay=``): its views go through the
runner's per-view step (combine, process, engine) as a resumed scan's recorded views do, and are
announced as documents again; the station is the recorded one (`capture.station.recorded_station`:
its calibration and camera URL, no device). The engine follows the live scan's recorded update
schedule, so with the same plan and seed the replay builds the same mesh.
"""

from __future__ import annotations

import dataclasses
import logging

from .plan import ScanPlan
from .recording import Recording, RecordingError, read_recording

log = logging.getLogger(__name__)


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
    return ScanRunner(plan, out_dir=out_dir, replay=recording, record=False, workers=workers,
                      executor=executor,
                      schedule=recorded_schedule(recording) if schedule == "recorded" else schedule)


def recorded_schedule(recording: Recording) -> list[int] | None:
    """The live engine's update schedule (view counts), from the last recorded mesh document;
    None when the recording has no mesh (then the replay's engine schedules its own)."""
    meshes = [d for d in recording.documents if d.get("kind") == "mesh"]
    if not meshes or "schedule" not in meshes[-1].get("figures", {}):
        return None
    return list(meshes[-1]["figures"]["schedule"])
