"""A scan's output folder: checked before the scan moves, written atomically at its end.

Files: ``recording.mcap`` (and later segments; `capture.recording`), ``mesh.ply`` (the final
mesh), ``engine/`` (the re-meshable fits, `capture.live.engine.remesh`), ``scan.json`` (plan,
calibration, station, state and reason, timings, mesh figures, quality against the simulated
object's true surface when there is one).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from reconstruct.io import write_bytes_atomic

from .plan import ScanPlan
from .quality import surface_quality, visible_samples
from .station import true_surface

log = logging.getLogger(__name__)

FORMAT = "scanstation-scan/1"
#: Bytes per depth pixel in the recording before compression (uint16 as base64) …
RECORDED_BYTES_PER_PIXEL = 8 / 3
#: … plus room for the mesh, the engine state and the report.
EXTRA_BYTES = 64 << 20


class OutputError(OSError):
    """The output folder cannot take the scan (the message names the folder and the cause)."""


class ScanOutputs:
    """The files of one scan in ``directory``."""

    def __init__(self, directory):
        self.directory = Path(directory)
        self.files: dict[str, str] = {}

    def check_writable(self) -> None:
        """Create the folder and write a probe file; `OutputError` names what failed."""
        where = self.directory
        try:
            where.mkdir(parents=True, exist_ok=True)
            fd, probe = tempfile.mkstemp(prefix=".write-test-", dir=where)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise OutputError(f"output folder {where} is not writable: "
                              f"{exc.strerror or exc}") from exc

    def check_space(self, plan: ScanPlan, intrinsics, record: bool = True) -> int:
        """Fail unless the disk has room for the recording (estimated from the image size)."""
        width, height = 2 * float(intrinsics[0][2]), 2 * float(intrinsics[1][2])
        per_view = plan.frames_per_view * width * height * RECORDED_BYTES_PER_PIXEL
        needed = int(EXTRA_BYTES + (plan.n_views * per_view if record else 0))
        free = shutil.disk_usage(self.directory).free
        if free < needed:
            raise OutputError(f"not enough space in {self.directory}: the scan needs about "
                              f"{needed / 1e6:.0f} MB, {free / 1e6:.0f} MB free")
        return needed

    def write_mesh(self, mesh, name: str = "mesh.ply") -> Path:
        path = write_bytes_atomic(self.directory / name, mesh.export(file_type="ply"))
        self.files["mesh"] = str(path)
        return path

    def write_engine(self, engine) -> Path:
        path = engine.save(self.directory)
        self.files["engine"] = str(path)
        return path

    def write_report(self, runner, state: str) -> dict[str, str]:
        """Write scan.json for ``runner`` ending in ``state``; returns the files written."""
        engine = runner.engine
        report = {
            "format": FORMAT,
            "scan_id": runner.scan_id,
            "state": state,
            "reason": runner.reason,
            "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "views_done": runner._views_done,
            "views_total": runner.plan.n_views,
            "plan": runner.plan.to_dict(),
            "calibration": json.loads(runner.station.calibration.to_json()),
            "station": runner.station.describe(),
            "timing": {
                "capture_s": getattr(runner, "_capture_s", None),
                "final_mesh_s": getattr(runner, "_final_mesh_s", None),
                "total_s": time.monotonic() - runner._started,
            },
            "mesh": engine.figures if engine is not None else None,
            "quality": None,
        }
        if state == "done" and engine is not None and engine.mesh is not None:
            report["quality"] = self.quality(runner)
        from .recording import segment_paths

        if self.directory.is_dir():
            segments = segment_paths(self.directory)
            if segments:
                self.files["recording"] = str(segments[0])
                report["segments"] = [str(p) for p in segments]
        self.files["report"] = str(self.directory / "scan.json")
        report["files"] = dict(self.files)
        write_bytes_atomic(self.directory / "scan.json", json.dumps(report, indent=1).encode())
        return dict(self.files)

    def quality(self, runner) -> dict | None:
        """Figures against the simulated object's true surface (None for real objects)."""
        truth = true_surface(runner.station.camera_url)
        if truth is None:
            return None
        started = time.perf_counter()
        shape = getattr(runner, "image_shape", None)
        if shape is None:
            k = runner.station.calibration.intrinsics
            shape = (int(round(2 * k[1, 2])), int(round(2 * k[0, 2])))
        visible = visible_samples(truth, runner.station.calibration, runner.plan.angles, shape,
                                  runner.plan.volume)
        raw = np.concatenate(runner._raw_points) if runner._raw_points else None
        figures = surface_quality(runner.engine.mesh, runner.engine.fitted_points, truth,
                                  visible, raw)
        log.info("quality against the true surface: completeness %.1f %% within %.2f mm, "
                 "denoise ratio %.2f (%.1f s)", 100 * figures["completeness_visible"],
                 figures["tau_mm"], figures["denoise_ratio"], time.perf_counter() - started)
        return figures
