"""Following one runner: its documents go to the scan's event channel and keep the job store's
view of the scan (state, progress, mesh version) current. Runs on the runner's threads.

Each intermediate mesh of the incremental engine is also written to ``mesh-live.ply`` in the
scan folder (atomically), so the web page shows the mesh growing while the table turns; the
runner writes the final ``mesh.ply`` when the scan is done.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from reconstruct.io import mesh_data

from .events import EventChannel
from .store import JobStore

log = logging.getLogger(__name__)

FINAL_MESH = "mesh.ply"
LIVE_MESH = "mesh-live.ply"


def as_dict(doc) -> dict[str, Any]:
    """A runner document as a JSON-safe dict (runners send `Document`s or dicts)."""
    return doc.to_dict() if hasattr(doc, "to_dict") else dict(doc)


def write_live_mesh(mesh, folder: Path) -> bool:
    """Write ``mesh`` (trimesh or None) to ``folder/mesh-live.ply`` atomically; False if not."""
    if mesh is None:
        return False
    partial = Path(folder) / f".{LIVE_MESH}.part"
    try:
        partial.write_bytes(mesh_data(mesh, "ply"))
        os.replace(partial, Path(folder) / LIVE_MESH)
    except OSError as exc:  # the live view is a bonus; the scan goes on
        log.warning("could not write the live mesh in %s: %s", folder, exc)
        return False
    return True


class ScanTracker:
    """A runner subscriber for scan ``scan_id`` (``replay``: a re-processing run). ``clean``
    rewrites the reasons and messages that clients see (no server paths); ``on_start`` is
    called on the runner's start document, before it is published (the scan now runs)."""

    def __init__(self, scan_id: str, runner, folder: Path, store: JobStore,
                 channel: EventChannel, replay: bool = False, clean=None, on_start=None):
        self.scan_id, self.runner, self.folder = scan_id, runner, Path(folder)
        self.store, self.channel, self.replay = store, channel, replay
        self.clean = clean or (lambda text: text)
        self.on_start = on_start

    def __call__(self, doc) -> None:
        data = as_dict(doc)
        for key in ("reason", "message"):
            if isinstance(data.get(key), str):
                data[key] = self.clean(data[key])
        kind = data.get("kind")
        if kind == "start" and self.on_start is not None:
            self.on_start()
        if kind == "mesh":
            self._mesh_updated(data.get("figures") or {})
        elif kind == "progress":
            self.store.update(self.scan_id, progress={
                key: data.get(key) for key in ("views_done", "views_total", "fraction")})
        elif kind in ("paused", "resumed") and not self.replay:
            self.store.update(self.scan_id, state="paused" if kind == "paused" else "running",
                              reason=data.get("message", ""))
        elif kind in ("error", "stop") and (data.get("reason") or data.get("message")):
            self.store.update(self.scan_id, reason=data.get("reason") or data.get("message"))
        self.channel.publish(data)  # after the store: a client reacting to it reads the news

    def _mesh_updated(self, figures: dict) -> None:
        engine = getattr(self.runner, "engine", None)  # in-process runner: write it here
        if engine is not None:
            write_live_mesh(engine.mesh, self.folder)
        if not (self.folder / LIVE_MESH).is_file():
            return
        record = self.store.get(self.scan_id)
        self.store.update(self.scan_id, mesh_version=record.mesh_version + 1,
                          mesh_params=self._params(record, figures, LIVE_MESH))

    def finished(self, state: str) -> None:
        """The runner ended in ``state``: a done scan's mesh is the final ``mesh.ply``."""
        if state != "done" or not (self.folder / FINAL_MESH).is_file():
            return
        record = self.store.get(self.scan_id)
        figures = getattr(getattr(self.runner, "engine", None), "figures", None) or {}
        self.store.update(self.scan_id, mesh_version=record.mesh_version + 1,
                          mesh_params=self._params(record, figures, FINAL_MESH))

    @staticmethod
    def _params(record, figures: dict, file: str) -> dict:
        planned = (record.request.get("plan") or {}).get("reconstruction") or {}
        return {"lam": figures.get("lam", planned.get("lam")),
                "depth": figures.get("depth", planned.get("depth")), "file": file}
