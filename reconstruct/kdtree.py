"""Nearest samples of the join's grid nodes, by pykdtree.

A re-mesh of an atlas evaluates its join's grid again round the samples that moved: a query of
the 8 nearest samples for tens of thousands of nodes, and of the nearest for as many more.
pykdtree answers them faster than scipy's cKDTree, with the same neighbours and distances
(sheets 22k, 38,000 nodes, 8 nearest of 31,000 samples, 2 threads: 20.6 ms against 31.6, and
1.4 ms against 7 to build the tree). Its threads are OpenMP's: `PointTree.query` sets them
for its own OpenMP runtime, call by call (``workers``), and leaves the others' (torch's,
BLAS's) as they are, whatever ``OMP_NUM_THREADS`` says.
"""

from __future__ import annotations

import os

import numpy as np
from pykdtree.kdtree import KDTree

#: Threads of the join's KD-tree queries (the machine has 2 cores; a join runs after its
#: charts, on its own).
QUERY_THREADS = 2


class PointTree:
    """``query`` of scipy's cKDTree over ``data`` (n, d) (k nearest, an upper bound on the
    distance, ``workers`` threads), answered by pykdtree. Picklable (the tree is built again
    from the points)."""

    def __init__(self, data):
        self.data = np.ascontiguousarray(data, dtype=np.float64)
        self.n, self.m = self.data.shape
        self._tree = KDTree(self.data) if self.n else None

    def query(self, x, k: int = 1, distance_upper_bound: float = np.inf, workers: int = 1):
        """Distances and indices of the ``k`` nearest points to each of ``x`` (q, d), (q,)
        each for k = 1 else (q, k), nearest first; beyond ``distance_upper_bound`` (or past
        the n points) the distance is inf and the index n, as cKDTree's."""
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, self.m)
        found = min(k, self.n)
        if found and len(x):
            _set_threads((os.cpu_count() or 1) if workers == -1 else max(int(workers), 1))
            bound = None if np.isinf(distance_upper_bound) else float(distance_upper_bound)
            distance, index = self._tree.query(x, k=found, distance_upper_bound=bound)
            distance, index = distance.reshape(len(x), found), index.astype(np.intp)
            index = index.reshape(len(x), found)
        else:
            distance, index = np.zeros((len(x), found)), np.zeros((len(x), found), np.intp)
        if found < k:  # fewer points than asked: as far as none
            distance = np.hstack([distance, np.full((len(x), k - found), np.inf)])
            index = np.hstack([index, np.full((len(x), k - found), self.n, np.intp)])
        return (distance[:, 0], index[:, 0]) if k == 1 else (distance, index)

    def __getstate__(self):
        return {"data": self.data}

    def __setstate__(self, state):
        self.__init__(state["data"])


def _set_threads(count: int) -> None:
    """Threads of pykdtree's next query in this thread (its OpenMP runtime's, not others')."""
    global _openmp
    if _openmp is None:
        from threadpoolctl import ThreadpoolController

        _openmp = [lib for lib in ThreadpoolController().lib_controllers
                   if lib.internal_api == "openmp" and "pykdtree" in lib.filepath]
    for lib in _openmp:
        lib.set_num_threads(count)


_openmp: list | None = None
