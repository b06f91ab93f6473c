"""A scan's patch fits, kept by patch name while the cloud grows, and the policy that refits them.

`PatchCache.job` decides per patch and update: keep the last fit (between views: until its
coverage grew by ``min_growth``; at the end: only a polished fit of the same points), or fit
again (a `FitJob`): warm-start the patch's own earlier network, or fit it anew, the first
patches with the paper's architecture search, the later ones training the architecture it found
(`patch_fit.fit_patch`); settled patches and the last update get polished fits. `PatchCache.run`
runs the jobs (on a process pool when given) and stores the results.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import time
import warnings

import numpy as np

from reconstruct.errors import ReconstructionWarning
from reconstruct.networks import n_parameters
from reconstruct.pipeline import SurfaceReconstructor

from ..plan import ReconstructionParams
from .cloud import voxel_keys
from .patch_fit import fit_patch

log = logging.getLogger(__name__)

#: At the end, a polished fit stands when its patch's coverage grew less than this since.
FINAL_GROWTH = 0.03

@dataclasses.dataclass
class PatchFit:
    """A patch's fit: the model, the sha1 of the points and their coverage it was fitted to."""

    model: SurfaceReconstructor
    digest: str
    coverage: int
    polished: bool = False


@dataclasses.dataclass(frozen=True)
class FitJob:
    """A patch to fit: its (n, 3) points, its earlier model (None: a first fit), polished?"""

    name: str
    points: np.ndarray
    previous: SurfaceReconstructor | None
    polish: bool


@dataclasses.dataclass(frozen=True)
class FitResult:
    """A job's outcome (from a worker): model None when it failed (``error`` says why)."""

    model: SurfaceReconstructor | None
    how: str  # "fresh", "fixed", "warm" or "failed"
    seconds: float
    error: str | None = None
    said: tuple[str, ...] = ()  # a worker's `ReconstructionWarning`s: said here, named


def _digest(points: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(points, dtype=np.float64).tobytes()).hexdigest()


def coverage_cells(points: np.ndarray, cell_mm: float) -> int:
    """Occupied cells of ``cell_mm`` among (n, 3) points: how much surface they cover."""
    return len(np.unique(voxel_keys(points, cell_mm))) if len(points) else 0


class PatchCache:
    """Fits by patch name, and the policy deciding reuse / warm start / fresh fit."""

    def __init__(self, params: ReconstructionParams):
        self.params = params
        self.fits: dict[str, PatchFit] = {}
        self.counts = {"fresh": 0, "fixed": 0, "warm": 0, "reused": 0, "failed": 0}
        self._said: dict[str, set[str]] = {}  # the warnings said of each patch
        #: The architecture the first searched patches found (the largest), then reused.
        self.layers: tuple[int, ...] | None = None

    def job(self, name: str, points: np.ndarray, final: bool, settled: bool) -> FitJob | None:
        """None when the stored fit stands, else the `FitJob` to run.

        A fit stands while the patch's coverage grew less than ``min_growth`` since it — at the
        end, or once the patch has settled (stopped growing), only a polished fit stands, and
        at the end only if the coverage grew less than ``FINAL_GROWTH``. Settled patches and
        the end get polished fits."""
        polish = final or settled
        known = self.fits.get(name)
        if known is not None:
            grown = coverage_cells(points, 2 * self.params.voxel_mm) / max(known.coverage, 1) - 1
            if known.digest == _digest(points):
                grown = 0.0
            limit = FINAL_GROWTH if final else self.params.min_growth
            if grown < limit and (known.polished or not polish):
                self.counts["reused"] += 1
                return None
        return FitJob(name, points, None if known is None else known.model, polish)

    def run(self, jobs: list[FitJob], executor=None) -> list[str]:
        """Fit the jobs (on ``executor`` when given) and store them; the names that failed."""
        p = self.params
        started = time.perf_counter()
        if executor is None:
            results = [_fit_job(job, p, self.layers) for job in jobs]
        else:
            futures = [executor.submit(_fit_job_in_worker, job, p, self.layers)
                       for job in jobs]
            results = [f.result() for f in futures]
        failed = []
        for job, result in zip(jobs, results, strict=True):
            self.counts[result.how] += 1
            for message in result.said:  # once a patch, not at each of its refits
                if message not in self._said.setdefault(job.name, set()):
                    self._said[job.name].add(message)
                    log.warning("patch %s: %s", job.name, message)
            if result.model is None:
                log.warning("patch %s: fit failed (%s); it stays open for now", job.name,
                            result.error)
                failed.append(job.name)
                continue
            log.info("patch %s: %s%s fit of %d points in %.1f s, layers %s", job.name,
                     "polished " if job.polish else "", result.how, len(job.points),
                     result.seconds, result.model.hidden_layers_)
            self.fits[job.name] = PatchFit(result.model, _digest(job.points),
                                           coverage_cells(job.points, 2 * p.voxel_mm),
                                           polished=job.polish)
        searched = [r.model.hidden_layers_ for r in results if r.how == "fresh"]
        if self.layers is None and searched:
            self.layers = max(searched, key=n_parameters)
            log.info("architecture %s from the search: the other patches train it", self.layers)
        if jobs:
            log.debug("%d patch fits in %.1f s", len(jobs), time.perf_counter() - started)
        return failed


def _fit_job(job: FitJob, params: ReconstructionParams, layers) -> FitResult:
    """Run one job (inline, or inside `_fit_job_in_worker`)."""
    started = time.perf_counter()
    try:
        model, how = fit_patch(job.points, job.previous, params, polish=job.polish,
                               layers=layers)
    except Exception as exc:  # one bad patch must not lose the whole mesh
        return FitResult(None, "failed", time.perf_counter() - started,
                         f"{type(exc).__name__}: {exc}")
    return FitResult(model, how, time.perf_counter() - started)


def _fit_job_in_worker(job: FitJob, params: ReconstructionParams, layers) -> FitResult:
    """`_fit_job` in a worker process, its `ReconstructionWarning`s returned with its result
    (the worker printed them to its stderr with a file and a line of code); others are
    said there as before."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ReconstructionWarning)
        result = _fit_job(job, params, layers)
    said = []
    for w in caught:
        if issubclass(w.category, ReconstructionWarning):
            said.append(str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return dataclasses.replace(result, said=tuple(dict.fromkeys(said)))
