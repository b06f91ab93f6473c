"""Re-meshing a finished scan with a new λ / boundary depth, through ONNX, with no training.

`capture.live.engine` saves the reconstruction (every patch's network and boundary state) in the
scan folder; loading it costs more than a re-mesh, so the last few loaded engines are kept, and
a λ slider moved by an operator re-meshes in milliseconds. Each refine writes
``mesh-lam{λ}-depth{d}.ply`` in the scan folder (as `capture.live.engine.remesh` does); the
folder keeps the `KEEP_REFINED` newest.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import os
import threading
from pathlib import Path

from .errors import Conflict, InvalidRequest

#: Refined meshes a scan folder keeps (the newest; the scan's own ``mesh.ply`` is kept too).
KEEP_REFINED = 8


class RefineFailed(InvalidRequest):
    """The new λ / depth give no mesh (e.g. the boundary spline collapses): 422, and the
    scan keeps its previous mesh."""


@dataclasses.dataclass(frozen=True)
class RefineResult:
    lam: float
    depth: int
    file: str  # mesh file name inside the scan folder
    figures: dict


class MeshRefiner:
    """Loaded engines by scan id (the ``cache_size`` most recent); one refine per scan at a time."""

    def __init__(self, cache_size: int = 4):
        self.cache_size = cache_size
        self._engines: collections.OrderedDict[str, object] = collections.OrderedDict()
        self._locks: dict[str, threading.Lock] = {}
        self._lock = threading.Lock()

    def remesh(self, scan_id: str, folder: Path, lam: float | None,
               depth: int | None) -> RefineResult:
        """Re-mesh and write the mesh; `Conflict` when the scan has no saved reconstruction,
        `RefineFailed` when the new parameters give no mesh."""
        from capture.live.engine import DamagedState, EngineError, IncrementalEngine
        from reconstruct.errors import ReconstructionError
        from reconstruct.io import mesh_data

        with self._lock:
            scan_lock = self._locks.setdefault(scan_id, threading.Lock())
        with scan_lock:
            with self._lock:
                engine = self._engines.get(scan_id)
                if engine is not None:
                    self._engines.move_to_end(scan_id)
            if engine is None:
                try:
                    engine = IncrementalEngine.load(folder)
                except DamagedState as exc:
                    raise Conflict(f"scan {scan_id}'s saved reconstruction is damaged or of "
                                   "another version: re-process the scan") from exc
                except EngineError as exc:
                    raise Conflict(f"scan {scan_id} has no saved reconstruction to refine") \
                        from exc
                with self._lock:
                    self._engines[scan_id] = engine
                    while len(self._engines) > self.cache_size:
                        self._engines.popitem(last=False)
            try:
                engine.remesh(lam, depth)  # on failure the engine keeps its last mesh
            except ReconstructionError as exc:
                cause = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise RefineFailed(f"refine with lam={lam}, depth={depth} failed: {cause}; "
                                   "the previous mesh is kept") from exc
            figures = dict(engine.figures)
            name = f"mesh-lam{figures['lam']:g}-depth{figures['depth']}.ply"
            partial = folder / f".{name}.part"
            partial.write_bytes(mesh_data(engine.mesh, "ply"))
            os.replace(partial, folder / name)  # a download never sees half a file
            _drop_old_refines(folder, name)
        return RefineResult(float(figures["lam"]), int(figures["depth"]), name, figures)

    def forget(self, scan_id: str) -> None:
        with self._lock:
            self._engines.pop(scan_id, None)
            self._locks.pop(scan_id, None)


def _drop_old_refines(folder: Path, current: str) -> None:
    """Keep the `KEEP_REFINED` newest refined meshes in ``folder`` (``current`` among them):
    a slider moved for an hour, or a client asking every λ, does not fill the disk."""
    refined = [path for path in folder.glob("mesh-lam*-depth*.ply") if path.name != current]
    refined.sort(key=lambda path: path.stat().st_mtime_ns, reverse=True)
    for path in refined[KEEP_REFINED - 1:]:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
