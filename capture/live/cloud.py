"""The merged cloud of a scan: views accumulate into one voxel grid in the object frame.

Each occupied voxel keeps the sum and count of the points that fell in it, so a surface seen by
many views averages down its noise and the cloud never grows past one point per voxel. Add one
view's points at a time (at most one point per voxel each, as `ViewProcessor` thins them): the
count is then the number of views that saw the voxel. The grid
is anchored at the origin, so merging is order-independent up to floating-point summation.

A surface that lies along a face of the grid, within a fraction of a voxel of it, falls in two
layers of voxels whose means stand a fraction of a voxel apart (the vase's top at z = 120 mm,
on a 2 mm voxel boundary: two layers 0.26 mm apart, their next neighbours 1.7 mm away): a
surface sampled twice. `points` takes each such pair as one point (`SPLIT_LAYERS`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Two voxels' means that are each other's nearest and nearer than this many voxels are one
#: surface split by a face of the grid: `VoxelCloud.points` gives their joint mean. (Means of
#: one surface's voxels stand about a voxel apart; two within a quarter of one come from the
#: parts of a surface on either side of a face, near-parallel to it.)
SPLIT_LAYERS = 0.25
_OFFSET = 1 << 20  # voxel indices in [-2^20, 2^20) per axis pack into one int64 key
_BITS = 21


def voxel_keys(points: np.ndarray, voxel_mm: float) -> np.ndarray:
    """(n,) int64 key of the voxel of each point (n, 3), mm."""
    cells = np.floor(np.asarray(points, dtype=np.float64) / voxel_mm).astype(np.int64) + _OFFSET
    if cells.size and (cells.min() < 0 or cells.max() >= 2 * _OFFSET):
        raise ValueError(f"points lie beyond ±{_OFFSET * voxel_mm:g} mm of the axis")
    return (cells[:, 0] << (2 * _BITS)) | (cells[:, 1] << _BITS) | cells[:, 2]


class VoxelCloud:
    """Accumulates (n, 3) point sets (mm) into voxels of ``voxel_mm``; `points` are the means."""

    def __init__(self, voxel_mm: float):
        if not voxel_mm > 0:
            raise ValueError(f"voxel_mm must be > 0, got {voxel_mm}")
        self.voxel_mm = float(voxel_mm)
        self._keys = np.empty(0, dtype=np.int64)
        self._sums = np.empty((0, 3))
        self._counts = np.empty(0, dtype=np.int64)
        self.n_added = 0

    def __len__(self) -> int:
        return len(self._keys)

    def add(self, points) -> int:
        """Merge (n, 3) points; returns the number of voxels that were empty before."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return 0
        before = len(self._keys)
        keys = np.concatenate([self._keys, voxel_keys(points, self.voxel_mm)])
        sums = np.concatenate([self._sums, points])
        counts = np.concatenate([self._counts, np.ones(len(points), dtype=np.int64)])
        unique, inverse = np.unique(keys, return_inverse=True)
        self._sums = np.stack([np.bincount(inverse, sums[:, i], len(unique)) for i in range(3)], 1)
        self._counts = np.bincount(inverse, counts, len(unique)).astype(np.int64)
        self._keys = unique
        self.n_added += len(points)
        return len(unique) - before

    def points(self, min_views: int = 1) -> np.ndarray:
        """(m, 3) float64 means of the voxels that at least ``min_views`` point sets reached
        (a stray point seen once stays out), ordered by voxel key; the two voxels of a surface
        split by a face of the grid give one, their joint mean (`SPLIT_LAYERS`), reached by
        the point sets of both (its views split between them)."""
        sums, counts = self._sums.copy(), self._counts.copy()
        keep = np.ones(len(counts), bool)
        if len(counts) >= 2:
            means = sums / counts[:, None]
            distance, nearest = cKDTree(means).query(means, 2)
            distance, nearest = distance[:, 1], nearest[:, 1]
            index = np.arange(len(means))
            first = ((nearest[nearest] == index) & (index < nearest)
                     & (distance < SPLIT_LAYERS * self.voxel_mm))
            second = nearest[first]
            sums[first] += sums[second]
            counts[first] += counts[second]
            keep[second] = False
        keep &= counts >= min_views
        return sums[keep] / counts[keep, None]

    def state(self) -> dict[str, np.ndarray]:
        return {"keys": self._keys, "sums": self._sums, "counts": self._counts}

    @classmethod
    def from_state(cls, voxel_mm: float, state: dict) -> VoxelCloud:
        cloud = cls(voxel_mm)
        cloud._keys = np.asarray(state["keys"], dtype=np.int64)
        cloud._sums = np.asarray(state["sums"], dtype=np.float64)
        cloud._counts = np.asarray(state["counts"], dtype=np.int64)
        return cloud
