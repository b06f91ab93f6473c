"""The incremental engine: views stream in, the mesh grows and refines while the object turns.

Views (object-frame points) merge into a `VoxelCloud`. After every ``update_every`` views, and
after the last view (`finish`), the engine reconstructs the closed object as patches
(`LivePatches`, fits kept in a `PatchCache`): a patch is first fitted once its coverage stops
growing, then it keeps its fit until it grows by ``min_growth`` (and is fine-tuned from its own
network: a warm start); the last update polishes every patch on the final points. Updates run in
order on one worker thread, so the meshes depend only on the views (a replay gives the same
mesh), never on timing. Each new mesh goes to ``on_mesh``. `remesh` re-meshes every patch
through its ONNX map with a new λ / depth: no training.

The final mesh of an object the sectors cannot mesh (the plan's ``surface``: "auto" when a
sector's fit is unfaithful — a mug's inside, a handle, an overhang — or "atlas") is an atlas of
charts fitted on the merged cloud (`reconstruct.atlas.AtlasReconstructor`, `atlas_fit`); the
live previews stay the sectors' (an atlas takes too long to refit every few views), and the
sectors' final polish is skipped when their earlier fits already ask for the atlas. `remesh`
then re-meshes the atlas's charts through their ONNX maps and joins them again.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import queue
import signal
import threading
import time
from pathlib import Path

import numpy as np
import trimesh

from reconstruct.atlas import AtlasReconstructor
from reconstruct.errors import ReconstructionError
from reconstruct.io import mesh_data, one_line, write_bytes_atomic
from reconstruct.pipeline import SurfaceReconstructor

from ..executors import make_executor
from ..plan import ReconstructionParams
from .atlas_fit import atlas_reason, fit_atlas
from .cloud import VoxelCloud
from .patch_cache import PatchCache, PatchFit
from .patches import LivePatches

log = logging.getLogger(__name__)

STATE_DIR = "engine"
ATLAS_FILE = "atlas.npz"  # in STATE_DIR, when the final mesh is an atlas
_STOP = object()


class EngineError(RuntimeError):
    """The engine failed or was used out of order (the message names the cause)."""


class DamagedState(EngineError):
    """A scan's saved reconstruction is there but cannot be loaded (a torn file, another
    version's fields)."""


@dataclasses.dataclass(frozen=True)
class Update:
    """A scheduled reconstruction: the merged (m, 3) points after ``views`` views."""

    points: np.ndarray
    views: int
    final: bool


class IncrementalEngine:
    """Merge views and keep an up-to-date mesh.

    params : `ReconstructionParams`.  on_mesh : callable(engine, figures) after each new mesh
    (from the worker thread).  background : run updates on a worker thread (else inline).
    workers : processes fitting patches in parallel (1: in the engine's thread). The result
    does not depend on it.  total_views : views the scan will have, when known: the update
    that would fall on the last view is left to `finish`.
    executor : a `concurrent.futures.Executor` for the fits instead of ``workers`` processes
        (`capture.executors.make_executor`: local processes or a Dask cluster); the caller
        shuts it down.
    schedule : view counts after which to update (a replay passes the live scan's, recorded in
        its mesh documents as ``figures["schedule"]``). None: every ``update_every`` views, and
        an update still queued when a newer one arrives is skipped, so the engine never lags
        more than one update behind the turntable.
    Attributes: ``mesh`` (trimesh.Trimesh or None), ``version`` (0 until the first mesh),
    ``surface`` ("sectors" or "atlas": how ``mesh`` was made), ``atlas`` (the fitted
    `AtlasReconstructor` when the final mesh is the atlas's, else None),
    ``figures`` (dict of the last update), ``cloud`` (`VoxelCloud`), ``views`` (count),
    ``view_points`` (each view's (n, 3) points as added, for the quality report),
    ``schedule_run`` (view counts of the updates run so far, the final one excluded).
    """

    def __init__(self, params: ReconstructionParams, on_mesh=None, background: bool = True,
                 workers: int = 1, total_views: int | None = None, schedule=None,
                 executor=None):
        self.params = params
        self.total_views = total_views
        self.schedule = None if schedule is None else sorted(int(v) for v in schedule)
        self.schedule_run: list[int] = []
        self.workers = int(workers)
        self._executor = executor  # injected (`capture.executors`): its owner shuts it down
        self._owns_executor = executor is None
        self.on_mesh = on_mesh
        self.cloud = VoxelCloud(params.voxel_mm)
        self.cache = PatchCache(params)
        self.patches = LivePatches(self.cache)
        self.mesh: trimesh.Trimesh | None = None
        self.surface = "sectors"
        self.atlas = None
        self.version = 0
        self.figures: dict = {}
        self.views = 0
        self.view_points: list[np.ndarray] = []
        self.error: BaseException | None = None
        self._last_update = 0  # views at the last scheduled update
        self._fitted_points: np.ndarray | None = None
        self._lock = threading.Lock()
        self._queue: queue.Queue = queue.Queue()
        self._thread = None
        self._abandoned = False
        if self._owns_executor:  # local spawn processes, torch imported while the scan starts
            self._executor = make_executor(None, self.workers)
        if background:
            self._thread = threading.Thread(target=self._work, name="scan-engine", daemon=True)
            self._thread.start()

    @property
    def fitted_points(self) -> np.ndarray | None:
        """(m, 3) the merged points the current mesh was fitted to, mm (None before a mesh)."""
        return self._fitted_points

    # -- feeding -------------------------------------------------------------------------------
    def add_view(self, points) -> bool:
        """Merge one view's (n, 3) object-frame points, mm; True when it scheduled an update."""
        self.cloud.add(points)
        self.view_points.append(points)
        self.views += 1
        p = self.params
        if self.schedule is not None:
            due = self.views in self.schedule
        else:
            due = bool(p.update_every) and self.views - self._last_update >= p.update_every
            due = due and self.views != self.total_views
        if due:
            self._schedule(final=False)
        return due

    def finish(self, timeout: float | None = None) -> trimesh.Trimesh | None:
        """Schedule the final reconstruction of all views and wait for every update."""
        self._schedule(final=True)
        self.wait(timeout)
        return self.mesh

    def _schedule(self, final: bool) -> None:
        self._last_update = self.views
        update = Update(self.cloud.points(self.params.min_views), self.views, final)
        if self._thread is None:
            self._run(update)
        else:
            self._queue.put(update)

    def wait(self, timeout: float | None = None) -> None:
        """Block until every scheduled update ran; re-raise the engine's failure if any."""
        if self._thread is not None:
            deadline = None if timeout is None else time.monotonic() + timeout
            with self._queue.all_tasks_done:
                while self._queue.unfinished_tasks:
                    left = None if deadline is None else deadline - time.monotonic()
                    if left is not None and left <= 0:
                        raise EngineError(f"reconstruction still running after {timeout} s")
                    self._queue.all_tasks_done.wait(left)
        if self.error is not None:
            raise EngineError(f"reconstruction failed: {self.error}") from self.error

    def cancel(self) -> None:
        """Drop updates not started yet (the one running finishes)."""
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                return
            self._queue.task_done()

    def close(self, wait: bool = True) -> None:
        """Stop the worker after the update in progress; safe to repeat. ``wait=False``
        abandons that update (a cancelled or failed scan drops its mesh: not waited for, its
        failure not reported)."""
        if self._thread is not None:
            self._abandoned = not wait
            self.cancel()
            self._queue.put(_STOP)
            if wait:
                self._thread.join()
            self._thread = None
        if self._executor is not None and self._owns_executor:
            workers = list(getattr(self._executor, "_processes", None) or {})
            self._executor.shutdown(wait=wait, cancel_futures=True)
            if not wait:  # its fits under way end with their processes (else the exit waits)
                _stop_processes(workers)
        self._executor = None

    # -- work ----------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            update = self._queue.get()
            try:
                if update is _STOP:
                    return
                stale = self.schedule is None and not update.final and not self._queue.empty()
                if self.error is None and not stale:  # (a newer update is waiting: skip)
                    self._run(update)
            except Exception as exc:  # kept and re-raised by wait(): the scan decides
                if self._abandoned:  # its scan ended: nobody waits for it
                    log.debug("abandoned reconstruction ended: %s", exc)
                else:
                    log.error("reconstruction failed: %s", exc)
                self.error = exc
            finally:
                self._queue.task_done()

    def _run(self, update: Update) -> None:
        points, views, final = update.points, update.views, update.final
        started = time.perf_counter()
        if not final:
            self.schedule_run.append(views)
        if len(points) < self.patches.split.min_points:  # nothing a patch could be fitted to
            log.info("update after %d views: %d points seen in %d views or more, too few to "
                     "mesh", views, len(points), self.params.min_views)
            return
        before = dict(self.cache.counts)
        # The sectors' earlier fits may already ask for the atlas: then no final polish.
        reason = atlas_reason(self.params, self._sector_models(), final)
        patches = None
        if reason is None:
            patches = self.patches.update(points, final=final, executor=self._executor)
            reason = atlas_reason(self.params, self._sector_models(), final)
        if reason is not None and self._run_atlas(points, views, reason, started):
            return
        if patches is None:  # the atlas failed: the sectors after all
            patches = self.patches.update(points, final=final, executor=self._executor)
        if len(patches.mesh.faces) == 0:
            log.info("update after %d views: no patch is ready yet", views)
            return
        counts = {k: v - before[k] for k, v in self.cache.counts.items()}
        self.surface, self.atlas = "sectors", None
        self._publish(patches.mesh, points, {
            "views": views,
            "final": final,
            "surface": "sectors",
            "points": len(points),
            "seconds": time.perf_counter() - started,
            "patches": len(patches.names) - len(patches.waiting),
            "patches_waiting": len(patches.waiting),
            **{f"patches_{k}": v for k, v in counts.items()},
            "schedule": list(self.schedule_run),
        })

    def _sector_models(self) -> dict:
        return {name: fit.model for name, fit in self.cache.fits.items()}

    def _run_atlas(self, points, views: int, reason: str, started: float) -> bool:
        """Fit the atlas on the final (m, 3) points and publish its mesh; False if it failed."""
        log.info("final mesh: an atlas of charts (%s)", reason)
        try:
            if self._executor is None:
                atlas, seconds, said = fit_atlas(points, self.params)
            else:
                atlas, seconds, said = self._executor.submit(fit_atlas, points,
                                                             self.params).result()
        except Exception as exc:  # the sectors' mesh is better than none
            log.warning("the atlas failed (%s: %s); the final mesh is the sectors'",
                        type(exc).__name__, exc)
            return False
        for line in said:
            log.warning("atlas: %s", line)
        self.surface, self.atlas = "atlas", atlas
        self._publish(atlas.mesh_, points, {
            "views": views,
            "final": True,
            "surface": "atlas",
            "atlas_reason": reason,
            "points": len(points),
            "seconds": time.perf_counter() - started,
            "atlas_s": seconds,
            "charts": len(atlas.charts_),
            "watertight": bool(atlas.watertight_),
            "euler": int(atlas.euler_),
            "schedule": list(self.schedule_run),
        })
        return True

    def _publish(self, mesh, points, figures: dict) -> None:
        with self._lock:
            self.mesh = mesh
            self._fitted_points = points
            self.version += 1
            self.figures = {"version": self.version, "vertices": len(mesh.vertices),
                            "faces": len(mesh.faces), **figures}
        log.debug("mesh v%d after %d views: %d faces (%.1f s)", self.version, figures["views"],
                 len(mesh.faces), figures["seconds"])
        if self.on_mesh is not None:
            self.on_mesh(self, dict(self.figures))

    # -- remesh and persistence -----------------------------------------------------------------
    def remesh(self, lam: float | None = None, depth: int | None = None) -> int:
        """Re-mesh every patch with a new λ and/or depth (ONNX, no training); new version."""
        self.wait()
        if self._fitted_points is None:
            raise EngineError("nothing to re-mesh: no mesh yet")
        lam = self.params.lam if lam is None else float(lam)
        depth = self.params.depth if depth is None else int(depth)
        started = time.perf_counter()
        if self.surface == "atlas":
            mesh = self.atlas.remesh(lam=lam, depth=depth)
        else:
            mesh = self.patches.remesh(self._fitted_points, lam, depth).mesh
        self._publish(mesh, self._fitted_points, {
            "views": self.figures.get("views", self.views), "final": True, "lam": lam,
            "depth": depth, "surface": self.surface, "points": len(self._fitted_points),
            "refined": True, "seconds": time.perf_counter() - started,
        })
        return self.version

    def save(self, directory) -> Path:
        """Write the cloud and every patch fit, or the atlas (re-meshable), to
        ``directory``/engine."""
        self.wait()
        target = Path(directory) / STATE_DIR
        target.mkdir(parents=True, exist_ok=True)
        names = sorted(self.cache.fits) if self.surface == "sectors" else []
        for i, name in enumerate(names):
            self.cache.fits[name].model.save(target / f"patch-{i}.npz")
        if self.surface == "atlas":
            self.atlas.save(target / ATLAS_FILE)
        np.save(target / "fitted_points.npy", self._fitted_points)
        (target / "engine.json").write_text(json.dumps({
            "params": self.params.__dict__, "patches": names, "surface": self.surface,
            "version": self.version, "figures": self.figures,
        }, indent=1))
        return target

    @classmethod
    def load(cls, directory) -> IncrementalEngine:
        """An engine that can `remesh` the reconstruction saved in ``directory``/engine."""
        source = Path(directory) / STATE_DIR
        try:
            meta = json.loads((source / "engine.json").read_text())
            points = np.load(source / "fitted_points.npy")
        except (OSError, ValueError) as exc:
            raise EngineError(f"{directory}: no saved reconstruction ({exc})") from exc
        try:
            return cls._from_saved(meta, points, source)
        except (OSError, ValueError, KeyError, TypeError, AttributeError,
                ReconstructionError) as exc:  # a torn file, another version's fields
            raise DamagedState(f"{directory}: its saved reconstruction is damaged or of another "
                              f"version ({one_line(exc)}); re-process the scan") from exc

    @classmethod
    def _from_saved(cls, meta: dict, points: np.ndarray, source: Path) -> IncrementalEngine:
        engine = cls(ReconstructionParams(**meta["params"]), background=False)
        for i, name in enumerate(meta["patches"]):
            model = SurfaceReconstructor.load(source / f"patch-{i}.npz")
            model.up = None  # a sector is oriented with its patch (saved before it said so)
            engine.cache.fits[name] = PatchFit(model, "", 0)
        if meta.get("surface") == "atlas":
            engine.surface, engine.atlas = "atlas", AtlasReconstructor.load(
                source / ATLAS_FILE)
        engine._fitted_points = points
        engine.version = int(meta["version"])
        engine.figures = dict(meta.get("figures", {}))
        return engine


def remesh(source, lam: float | None = None, depth: int | None = None):
    """Re-mesh without retraining. ``source``: an `IncrementalEngine` (returns the new mesh
    version) or a scan directory (writes and returns ``mesh-lam{λ}-depth{d}.ply`` beside it)."""
    if isinstance(source, IncrementalEngine):
        return source.remesh(lam, depth)
    engine = IncrementalEngine.load(source)
    engine.remesh(lam, depth)
    f = engine.figures
    path = Path(source) / f"mesh-lam{f['lam']:g}-depth{f['depth']}.ply"
    write_bytes_atomic(path, mesh_data(engine.mesh, "ply"))
    return path


def _stop_processes(pids) -> None:
    """End the worker processes ``pids`` of a `ProcessPoolExecutor` that was shut down (by
    pid: its own ``terminate_workers``, from Python 3.14, finds none once it is shut down)."""
    for pid in pids:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGTERM)
