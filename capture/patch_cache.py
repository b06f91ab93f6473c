"""Closed-object patches that remember their fits while the cloud grows, fitted in parallel.

`CachedPatches` is `PatchReconstructor` (sectors + cap, trimmed and zipped) run in two passes
over the same cloud: the first only collects each patch's points; the `PatchCache` then decides
per patch — keep the last fit (between views: until its coverage grew by ``min_growth``; at the
end: only a polished fit of the same points), warm-start the patch's own earlier network, or fit
it anew: the first patches with the paper's architecture search, the later ones training the
architecture it found; the last update polishes every patch (`warm_start.fit_patch`) — and runs
those fits on a process pool; the second pass trims and merges the fits. A patch gets its first fit
once its coverage stopped growing (by less than ``min_growth`` since the previous update) and a
sector's reached ``READY_SHARE`` of the largest sector's: a first fit on a partly seen patch
picks a poor network that later fine-tuning does not repair (measured), so it waits; at the end
every patch with enough points is fitted. In re-mesh mode
every patch re-meshes its stored fit through ONNX (new λ / depth, no training).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import time

import numpy as np
import trimesh

from reconstruct.networks import n_parameters
from reconstruct.pipeline import SurfaceReconstructor

from .patches import PatchReconstructor
from .plan import ReconstructionParams
from .warm_start import fit_patch

log = logging.getLogger(__name__)

#: A sector's first fit also waits until its coverage is this share of the largest sector's.
READY_SHARE = 0.6
#: At the end, a polished fit stands when its patch's coverage grew less than this since.
FINAL_GROWTH = 0.03

@dataclasses.dataclass
class PatchFit:
    model: SurfaceReconstructor
    digest: str
    coverage: int
    polished: bool = False


def _digest(points: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(points, dtype=np.float64).tobytes()).hexdigest()


def _coverage(points: np.ndarray, cell_mm: float) -> int:
    return len(np.unique(np.floor(points / cell_mm).astype(np.int64), axis=0))


class PatchCache:
    """Fits by patch name, and the policy deciding reuse / warm start / fresh fit."""

    def __init__(self, params: ReconstructionParams):
        self.params = params
        self.fits: dict[str, PatchFit] = {}
        self.counts = {"fresh": 0, "fixed": 0, "warm": 0, "reused": 0, "failed": 0}
        #: The architecture the first searched patches found (the largest), then reused.
        self.layers: tuple[int, ...] | None = None

    def job(self, name: str, points: np.ndarray, final: bool, settled: bool):
        """None when the stored fit stands, else (name, points, previous model or None, polish).

        A fit stands while the patch's coverage grew less than ``min_growth`` since it — at the
        end, or once the patch has settled (stopped growing), only a polished fit stands, and
        at the end only if the coverage grew less than ``FINAL_GROWTH``. Settled patches and
        the end get polished fits."""
        polish = final or settled
        known = self.fits.get(name)
        if known is not None:
            grown = _coverage(points, 2 * self.params.voxel_mm) / max(known.coverage, 1) - 1
            if known.digest == _digest(points):
                grown = 0.0
            limit = FINAL_GROWTH if final else self.params.min_growth
            if grown < limit and (known.polished or not polish):
                self.counts["reused"] += 1
                return None
        return name, points, None if known is None else known.model, polish

    def run(self, jobs, executor=None) -> list[str]:
        """Fit the jobs (on ``executor`` when given) and store them; the names that failed."""
        p = self.params
        started = time.perf_counter()
        if executor is None:
            results = [_fit_job(*job[1:], p, self.layers) for job in jobs]
        else:
            futures = [executor.submit(_fit_job, *job[1:], p, self.layers) for job in jobs]
            results = [f.result() for f in futures]
        failed = []
        for (name, points, _, polish), (model, how, seconds, error) in zip(jobs, results,
                                                                           strict=True):
            self.counts[how] += 1
            if model is None:
                log.warning("patch %s: fit failed (%s); it stays open for now", name, error)
                failed.append(name)
                continue
            log.info("patch %s: %s%s fit of %d points in %.1f s, layers %s", name,
                     "polished " if polish else "", how, len(points), seconds,
                     model.hidden_layers_)
            self.fits[name] = PatchFit(model, _digest(points),
                                       _coverage(points, 2 * p.voxel_mm), polished=polish)
        searched = [r[0].hidden_layers_ for r in results if r[1] == "fresh"]
        if self.layers is None and searched:
            self.layers = max(searched, key=n_parameters)
            log.info("architecture %s from the search: the other patches train it", self.layers)
        if jobs:
            log.debug("%d patch fits in %.1f s", len(jobs), time.perf_counter() - started)
        return failed


def _fit_job(points, previous, final, params, layers):
    """(model or None, "fresh" / "fixed" / "warm" / "failed", seconds, error): in a worker."""
    started = time.perf_counter()
    try:
        model, how = fit_patch(points, previous, params, polish=final, layers=layers)
    except Exception as exc:  # one bad patch must not lose the whole mesh
        return None, "failed", time.perf_counter() - started, f"{type(exc).__name__}: {exc}"
    return model, how, time.perf_counter() - started, None


class CachedPatches(PatchReconstructor):
    """`PatchReconstructor` whose patches come from a `PatchCache` (see the module docstring).

    After `fit_cloud` / `remesh_cloud`: ``waiting_`` lists the patches left open (too few
    points, not ready, or failed); the rest as in `PatchReconstructor`.
    """

    def __init__(self, cache: PatchCache, n_sectors: int = 6, overlap_deg: float = 20.0,
                 cap_fraction: float = 0.2, cap_overlap_mm: float | None = None,
                 min_points: int = 50):
        super().__init__(n_sectors=n_sectors, overlap_deg=overlap_deg, cap_fraction=cap_fraction,
                         cap_overlap_mm=cap_overlap_mm, min_points=min_points)
        self.cache = cache
        self._mode: tuple = ("collect", False)
        self._seen: dict[str, int] = {}  # coverage of each patch at the previous update

    @classmethod
    def for_params(cls, cache: PatchCache) -> CachedPatches:
        p = cache.params
        return cls(cache, n_sectors=p.n_sectors, overlap_deg=p.overlap_deg,
                   cap_fraction=p.cap_fraction, cap_overlap_mm=p.cap_overlap_mm,
                   min_points=p.min_patch_points)

    def fit_cloud(self, points, final: bool, executor=None) -> CachedPatches:
        """Update the fits for (n, 3) object-frame points, then trim and merge them."""
        self._mode, self._collected = ("collect", final), []
        self.fit(points)
        ready, settled = self._ready(final)
        jobs = [job for name, pts, _, _ in self._collected if name in ready
                if (job := self.cache.job(name, pts, final, name in settled)) is not None]
        self.cache.run(jobs, executor)  # a failed patch keeps its earlier fit, if any
        self._mode, self.waiting_ = ("merge", ready), []
        return self.fit(points)

    def remesh_cloud(self, points, lam: float, depth: int) -> CachedPatches:
        """Re-mesh every stored fit with a new λ / depth and merge (no training)."""
        for fit in self.cache.fits.values():
            fit.model.remesh(lam=lam, depth=depth)
        self._mode, self.waiting_ = ("merge", set(self.cache.fits)), []
        return self.fit(points)

    def _ready(self, final: bool) -> tuple[set[str], set[str]]:
        """(patches to fit now, patches that stopped growing). To fit: all at the end; else
        those fitted before and new ones that settled (coverage grew less than ``min_growth``
        since the previous update) with ``READY_SHARE`` of the largest sector's coverage, or
        that reached the largest sector's coverage (within ``min_growth``)."""
        growth = 1 + self.cache.params.min_growth
        sectors = sorted((c for _, _, c, cap in self._collected if not cap), reverse=True)
        largest = sectors[0] if sectors else 0
        ready, settled = set(), set()
        for name, _, coverage, cap in self._collected:
            before, self._seen[name] = self._seen.get(name), coverage
            if before is not None and coverage < before * growth:
                settled.add(name)
            big = cap or coverage >= READY_SHARE * largest
            caught_up = not cap and len(sectors) > 1 and coverage < largest and \
                coverage >= largest / growth
            if final or name in self.cache.fits or (name in settled and big) or caught_up:
                ready.add(name)
        return ready, settled

    def _fit_patch(self, name, points, mask, planes, reference_z):
        if self._mode[0] == "collect":
            if mask.sum() >= self.min_points:
                coverage = _coverage(points[mask], 2 * self.cache.params.voxel_mm)
                self._collected.append((name, points[mask], coverage, reference_z is not None))
            return _empty()
        if name not in self._mode[1] or name not in self.cache.fits:
            self.waiting_.append(name)
            return _empty()
        self._current = name
        return super()._fit_patch(name, points, mask, planes, reference_z)

    def _new_reconstructor(self):
        return _StoredFit(self.cache.fits[self._current].model)

    def _merge(self, meshes, bounds, cap_height) -> trimesh.Trimesh:
        if not any(len(m.faces) for m in meshes):
            self.n_seam_faces_ = 0
            return _empty()
        return super()._merge(meshes, bounds, cap_height)


class _StoredFit:
    """Hands a stored fit's mesh to `PatchReconstructor._fit_patch` (estimator protocol)."""

    def __init__(self, model: SurfaceReconstructor):
        self.mesh_ = model.mesh_

    def fit(self, points):
        return self


def _empty() -> trimesh.Trimesh:
    return trimesh.Trimesh(np.empty((0, 3)), np.empty((0, 3), dtype=int), process=False)
