"""A scan's output folder: checked before the scan moves, written atomically at its end.

Files: ``recording.mcap`` (and later segments; `capture.recording`), ``mesh.ply`` (the final
mesh), ``cloud.ply`` (the merged, calibrated points it was fitted to), ``engine/`` (the
re-meshable fits, `capture.live.engine.remesh`), ``scan.json`` (plan, calibration, station,
state and reason, timings, mesh figures, quality against the simulated object's true surface
when there is one; written by `capture.report.ScanReport`).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path

from reconstruct.io import cloud_data, mesh_data, write_bytes_atomic

from .plan import ScanPlan

log = logging.getLogger(__name__)

#: Bytes per depth pixel in the recording before compression (uint16 as base64) …
RECORDED_BYTES_PER_PIXEL = 8 / 3
#: … plus room for the mesh, the engine state and the report.
EXTRA_BYTES = 64 << 20


#: What a scan writes in its folder besides its recording's segments.
NAMES = ("mesh.ply", "cloud.ply", "scan.json", "engine")


class OutputError(OSError):
    """The output folder cannot take the scan (the message names the folder and the cause)."""


class ScanOutputs:
    """The files of one scan in ``directory``."""

    def __init__(self, directory):
        self.directory = Path(directory)
        self.files: dict[str, str] = {}

    def held(self) -> list[str]:
        """The names of a scan's files (`NAMES`) the folder already holds."""
        return [name for name in NAMES if (self.directory / name).exists()]

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
        path = write_bytes_atomic(self.directory / name, mesh_data(mesh, "ply"))
        self.files["mesh"] = str(path)
        return path

    def write_cloud(self, points, name: str = "cloud.ply") -> Path:
        """The merged, calibrated cloud (m, 3) mm the mesh was fitted to, for other tools."""
        path = write_bytes_atomic(self.directory / name, cloud_data(points))
        self.files["cloud"] = str(path)
        return path

    def write_engine(self, engine) -> Path:
        path = engine.save(self.directory)
        self.files["engine"] = str(path)
        return path

    @property
    def report_path(self) -> Path:
        return self.directory / "scan.json"

    def segments(self) -> list[Path]:
        """The recording's segments in the folder (none for a replay)."""
        from .recording import segment_paths

        return segment_paths(self.directory) if self.directory.is_dir() else []

    def final_files(self) -> dict[str, str]:
        """The files the scan leaves: those written, the recording, and the report
        (`capture.report.ScanReport` writes it on the stop document that lists them)."""
        segments = self.segments()
        if segments:
            self.files["recording"] = str(segments[0])
        self.files["report"] = str(self.report_path)
        return dict(self.files)
