"""A job-store row rebuilt from a scan folder (the store was damaged, emptied or lost a row).

A scan folder holds what the row held: ``scan.json`` (written when the scan ended: state,
reason, views, plan) and the recording (plan, station, every completed view). A folder with a
recording but no report is a scan that was cut off: ``interrupted``, resumable from its views.
A folder with neither is kept as ``failed`` with that said, never dropped.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

from .records import FINAL_STATES, ScanRecord

log = logging.getLogger(__name__)

SCAN_FOLDER = re.compile(r"^[0-9a-f]{16}$")
REBUILT = "rebuilt from its folder after the job store was damaged"


def record_from_folder(folder: Path, out_dir: str) -> ScanRecord:
    """The scan of ``folder`` (named by its 16-hex-digit id) as a job-store record."""
    created = folder.stat().st_mtime
    report = _report(folder)
    plan, views_done, state, reason, station = None, 0, "failed", "", {}
    if report is not None:
        plan, station = report.get("plan"), report.get("station") or {}
        views_done = int(report.get("views_done") or 0)
        state = report.get("state") if report.get("state") in FINAL_STATES else "interrupted"
        reason = str(report.get("reason") or "")
    recording = _recording(folder)
    if recording is not None:
        plan = plan or recording.plan.to_dict()
        station = station or recording.station
        views_done = max(views_done, len({v.index for v in recording.views}))
        if report is None:
            state, reason = "interrupted", "cut off before it ended; resumable from its recording"
    elif report is None:
        reason = "no recording or report in its folder (it never started)"
    plan = plan if isinstance(plan, dict) else {}
    total = len(plan.get("angles") or ())
    mesh = "mesh.ply" if (folder / "mesh.ply").is_file() else None
    from .schemas import device_keys

    return ScanRecord(
        id=folder.name, state=state, out_dir=out_dir, created=created, updated=created,
        devices=device_keys(station.get("camera"), station.get("turntable")),
        # no device URLs: a resume reads the station from the recording
        request={"plan": plan, "camera_url": None, "turntable_url": None, "object": None},
        reason=f"{reason} ({REBUILT})" if reason else REBUILT,
        progress={"views_done": views_done, "views_total": total,
                  "fraction": views_done / total if total else 0.0},
        mesh_version=1 if mesh else 0,
        mesh_params={"file": mesh} if mesh else {},
    )


def _report(folder: Path) -> dict | None:
    try:
        data = json.loads((folder / "scan.json").read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _recording(folder: Path):
    from capture.recording import RecordingError, read_recording, segment_paths

    if not segment_paths(folder):
        return None
    try:
        return read_recording(folder)
    except (RecordingError, OSError) as exc:
        log.warning("%s: recording unreadable while rebuilding its row: %s", folder.name, exc)
        return None
