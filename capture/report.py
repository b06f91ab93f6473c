"""``scan.json``: a document subscriber that writes a scan's report when its stop document arrives.

As bluesky's file writers do, `ScanReport` builds the report from the documents: the start
document (scan id, plan, calibration, station), the view and progress documents (image size, end
of capture), the mesh documents and the stop document (state, reason, views, files). What no
document carries is handed to it when it is made: the scan's folder (`ScanOutputs`), the engine
(the final mesh and the points it was fitted to, for the quality figures against a simulated
object's true surface) and the run's start time. A report that cannot be written is logged; the
scan's outcome stands.
"""

from __future__ import annotations

import collections
import json
import logging
import time

import numpy as np

from reconstruct.io import write_bytes_atomic

from .calibration import Calibration
from .documents import Document, StartDocument, StopDocument
from .outputs import ScanOutputs
from .plan import ScanPlan
from .quality import surface_quality, visible_samples
from .station import true_surface

log = logging.getLogger(__name__)

FORMAT = "scanstation-scan/1"


class ScanReport:
    """Writes ``scan.json`` into ``outputs.directory`` on the stop document.

    engine : the scan's `IncrementalEngine` (None: capture only).  started : `time.monotonic()`
    when the run started (default: when the start document arrives).  image_shape : (H, W) of
    views this run does not announce (a resumed scan's recorded views)."""

    def __init__(self, outputs: ScanOutputs, engine=None, started: float | None = None,
                 image_shape: tuple[int, int] | None = None):
        self.outputs = outputs
        self.engine = engine
        self.image_shape = image_shape
        self._started = started
        self._start: StartDocument | None = None
        self._captured: float | None = None  # monotonic time at the end of capture
        self._final_mesh_s: float | None = None
        self._limits: collections.Counter = collections.Counter()  # views reaching each

    def __call__(self, document: Document) -> None:
        now = time.monotonic()
        kind = document.kind
        if kind == "start":
            self._start = document
            self._started = now if self._started is None else self._started
            self._captured = now
        elif kind == "view" and document.frames:
            self.image_shape = tuple(np.shape(document.frames[0]))
        elif kind == "progress":
            self._captured = now
            self._limits.update(document.view_limits)
        elif kind == "mesh" and document.final and self._final_mesh_s is None:
            self._final_mesh_s = now - self._captured
        elif kind == "stop" and self._start is not None:
            try:
                self.write(document, now)
            except Exception as exc:
                log.error("could not write scan.json: %s", exc)

    def write(self, stop: StopDocument, now: float) -> None:
        start = self._start
        plan = ScanPlan.from_dict(start.plan)
        captured = stop.views_done >= stop.views_total
        report = {
            "format": FORMAT,
            "scan_id": start.scan_id,
            "state": stop.state,
            "reason": stop.reason,
            "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "views_done": stop.views_done,
            "views_total": stop.views_total,
            "plan": start.plan,
            "calibration": start.calibration,
            "station": start.station,
            "timing": {
                "capture_s": self._captured - self._started if captured else None,
                "final_mesh_s": self._final_mesh_s,
                "total_s": now - self._started,
            },
            "limits_reached": dict(self._limits),  # views where the object reached each
            "mesh": self.engine.figures if self.engine is not None else None,
            "quality": None,
        }
        engine = self.engine
        if stop.state == "done" and engine is not None and engine.mesh is not None:
            calibration = Calibration.from_json(json.dumps(start.calibration))
            report["quality"] = self.quality(plan, calibration, start.station.get("camera"))
        segments = self.outputs.segments()
        if segments:
            report["segments"] = [str(p) for p in segments]
        report["files"] = dict(stop.files)
        write_bytes_atomic(self.outputs.report_path, json.dumps(report, indent=1).encode())

    def quality(self, plan: ScanPlan, calibration: Calibration, camera_url) -> dict | None:
        """Figures against the simulated object's true surface (None for real objects)."""
        truth = true_surface(camera_url)
        if truth is None:
            return None
        started = time.perf_counter()
        shape = self.image_shape
        if shape is None:
            k = calibration.intrinsics
            shape = (int(round(2 * k[1, 2])), int(round(2 * k[0, 2])))
        visible = visible_samples(truth, calibration, plan.angles, shape, plan.volume)
        views = self.engine.view_points
        raw = np.concatenate(views) if views else None
        figures = surface_quality(self.engine.mesh, self.engine.fitted_points, truth, visible,
                                  raw)
        log.info("quality against the true surface: completeness %.1f %% within %.2f mm, "
                 "denoise ratio %.2f (%.1f s)", 100 * figures["completeness_visible"],
                 figures["tau_mm"], figures["denoise_ratio"], time.perf_counter() - started)
        return figures
