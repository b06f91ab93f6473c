"""A growing scan's closed-object patches: split, choose which to fit, fit, trim and merge.

Each update splits the merged cloud into sectors and a cap (`reconstruct.patches.PatchSplit`),
chooses the patches ready for a fit (`LivePatches.ready`), lets the `PatchCache` decide which
need a new fit and run them, then trims every fitted patch with its planes and merges them
(`reconstruct.patches.merge`). A patch gets its first fit once its coverage stopped growing (by
less than ``min_growth`` since the previous update) and a sector's reached ``READY_SHARE`` of
the largest sector's: a first fit on a partly seen patch picks a poor network that later
fine-tuning does not repair (measured), so it waits; at the end every patch with enough points
is fitted. `LivePatches.remesh` re-meshes every stored fit through ONNX (new λ / depth, no
training) and merges them on the split of the points they were fitted to (kept from the update
that made them: a λ slider never re-splits the cloud).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from reconstruct.patches import PatchLayout, PatchSplit, empty_mesh, merge, trim

from .patch_cache import PatchCache, coverage_cells

#: A sector's first fit also waits until its coverage is this share of the largest sector's.
READY_SHARE = 0.6


@dataclasses.dataclass(frozen=True)
class PatchPoints:
    """A patch with enough points: its (n, 3) points and their coverage (cells of 2 voxels)."""

    name: str
    points: np.ndarray
    coverage: int
    is_cap: bool


@dataclasses.dataclass(frozen=True)
class PatchUpdate:
    """The merged mesh of an update, every patch's name, and the patches left open."""

    mesh: trimesh.Trimesh
    names: list[str]
    waiting: list[str]


class LivePatches:
    """The patches of one scan (see the module docstring); fits live in ``cache``."""

    def __init__(self, cache: PatchCache):
        p = cache.params
        self.cache = cache
        self.split = PatchSplit(n_sectors=p.n_sectors, overlap_deg=p.overlap_deg,
                                cap_fraction=p.cap_fraction, cap_overlap_mm=p.cap_overlap_mm,
                                min_points=p.min_patch_points)
        self.layout: PatchLayout | None = None  # the last split, of ``self._split_points``
        self._split_points: np.ndarray | None = None
        self._seen: dict[str, int] = {}  # coverage of each patch at the previous update

    def update(self, points, final: bool, executor=None) -> PatchUpdate:
        """Fit what needs fitting for (n, 3) object-frame points (on ``executor`` when given),
        then trim and merge the fits."""
        self._split_once(points)
        points = np.asarray(points, dtype=np.float64)  # (split_once checked them)
        cell = 2 * self.cache.params.voxel_mm
        present = [PatchPoints(patch.name, points[patch.mask],
                               coverage_cells(points[patch.mask], cell), patch.is_cap)
                   for patch in self.layout.patches
                   if patch.mask.sum() >= self.split.min_points]
        ready, settled = self.ready(present, final)
        jobs = [job for patch in present if patch.name in ready
                if (job := self.cache.job(patch.name, patch.points, final,
                                          patch.name in settled)) is not None]
        self.cache.run(jobs, executor)  # a failed patch keeps its earlier fit, if any
        return self._merged(ready)

    def remesh(self, points, lam: float, depth: int) -> PatchUpdate:
        """Re-mesh every stored fit with a new λ / depth and merge them on the split of the
        (n, 3) ``points`` they were fitted to (no training)."""
        self._split_once(points)
        for fit in self.cache.fits.values():
            fit.model.remesh(lam=lam, depth=depth)
        return self._merged(set(self.cache.fits))

    def _split_once(self, points) -> None:
        """Split ``points`` unless the current layout is theirs (the same array)."""
        if points is not self._split_points:
            self.layout = self.split.split(points)
            self._split_points = points

    def ready(self, present: list[PatchPoints], final: bool) -> tuple[set[str], set[str]]:
        """(patches to fit now, patches that stopped growing). To fit: all at the end; else
        those fitted before and new ones that settled (coverage grew less than ``min_growth``
        since the previous update) with ``READY_SHARE`` of the largest sector's coverage, or
        that reached the largest sector's coverage (within ``min_growth``)."""
        growth = 1 + self.cache.params.min_growth
        sectors = sorted((p.coverage for p in present if not p.is_cap), reverse=True)
        largest = sectors[0] if sectors else 0
        ready, settled = set(), set()
        for patch in present:
            name, coverage = patch.name, patch.coverage
            before, self._seen[name] = self._seen.get(name), coverage
            if before is not None and coverage < before * growth:
                settled.add(name)
            big = patch.is_cap or coverage >= READY_SHARE * largest
            caught_up = not patch.is_cap and len(sectors) > 1 and coverage < largest and \
                coverage >= largest / growth
            if final or name in self.cache.fits or (name in settled and big) or caught_up:
                ready.add(name)
        return ready, settled

    def _merged(self, ready: set[str]) -> PatchUpdate:
        meshes, waiting = [], []
        for patch in self.layout.patches:
            fit = self.cache.fits.get(patch.name) if patch.name in ready else None
            if fit is None:
                waiting.append(patch.name)
                meshes.append(empty_mesh())
            else:
                meshes.append(trim(fit.model.mesh_, patch))
        mesh, _ = merge(meshes, self.layout)
        return PatchUpdate(mesh, [p.name for p in self.layout.patches], waiting)
