"""The files a scan offers for download: its mesh (in four formats), recording and report.

Every path is built by the daemon from fixed names under the scan folder and checked, after
resolving symlinks, to stay inside that folder: nothing a client sends (or a tampered job row
holds) can name a file elsewhere.
"""

from __future__ import annotations

from pathlib import Path

import trimesh

from .errors import OutsideScanFolder, Unavailable

REPORT = "scan.json"
MEDIA_TYPES = {
    "ply": "application/octet-stream",
    "obj": "model/obj",
    "stl": "model/stl",
    "glb": "model/gltf-binary",
}


def inside(folder: Path, name: str) -> Path:
    """``folder/name`` resolved; `OutsideScanFolder` when it would lie outside ``folder``."""
    root = Path(folder).resolve()
    path = (root / name).resolve()
    if not path.is_relative_to(root) or path == root:
        raise OutsideScanFolder(f"{name!r} is not a file of this scan")
    return path


def existing(folder: Path, name: str, what: str) -> Path:
    path = inside(folder, name)
    if not path.is_file():
        raise Unavailable(f"this scan has no {what} yet")
    return path


def mesh_file(folder: Path, name: str | None) -> Path:
    """The scan's current mesh (``name`` from the job store, else the scan's ``mesh.ply``)."""
    return existing(folder, name or "mesh.ply", "mesh")


def mesh_bytes(path: Path, fmt: str) -> bytes:
    """The mesh at ``path`` converted to ``fmt`` (ply, obj, stl, glb)."""
    if fmt not in MEDIA_TYPES:
        raise ValueError(f"unknown mesh format {fmt!r} (known: {', '.join(MEDIA_TYPES)})")
    from reconstruct.io import mesh_data

    return mesh_data(trimesh.load(path, force="mesh", process=False), fmt, name=path.name)


def recording_segments(folder: Path) -> list[Path]:
    """The scan's recording segments in order (a resumed scan has more than one)."""
    from capture.recording import segment_paths

    if not Path(folder).is_dir():
        return []
    return [inside(folder, path.name) for path in segment_paths(folder)]


def recording_file(folder: Path, segment: int) -> Path:
    segments = recording_segments(folder)
    if not segments:
        raise Unavailable("this scan has no recording yet")
    if not 1 <= segment <= len(segments):
        raise Unavailable(f"no recording segment {segment} (this scan has {len(segments)})")
    return segments[segment - 1]


def report_file(folder: Path) -> Path:
    return existing(folder, REPORT, "report")


def available(folder: Path, mesh_name: str | None) -> dict:
    """What can be downloaded now (for the scan's JSON)."""
    def exists(name):
        try:
            return inside(folder, name).is_file()
        except OutsideScanFolder:
            return False

    return {
        "mesh": exists(mesh_name or "mesh.ply"),
        "recording_segments": len(recording_segments(folder)),
        "report": exists(REPORT),
    }
