"""The shape a chart's network left in its points' residuals, put back into its samples.

A chart's network smooths what it cannot hold: the scanned dragon's scales and crevices of
1–3 mm leave its points' residuals alike over a few spacings, where noise leaves them
independent. `ResidualDetail` keeps a chart's points (m, 3) and their signed residuals from
its mesh, and moves a sample along its normal by the kernel average of the residuals of the
points round it, shrunk by the share of that average the shape explains rather than the noise
(a Wiener gain): the part of the residuals' variance their neighbours along the mesh share
(`faithfulness.shared_along`) against the noise left in the average. A chart that holds its
shape (a smooth torus's: nothing shared) is left as it is, to the last bit; so is one whose
points lie in two layers about it (`faithfulness.LAYERED_KURTOSIS`: the two faces of a plate
charted once, which share their residuals where one face's points crowd the other's: the
sheets at σ 0.2 %, 20k, Chamfer 0.330 / 0.314 at seeds 0 / 1 took 0.355 / 0.345).

bench.atlas 20k, σ 0.5 %, seeds 0 / 1 / 2, Chamfer-L1 without / with: the scanned dragon
0.328 / 0.314, 0.332 / 0.323, 0.344 / 0.330 (denoise 0.55-0.59 -> 0.53-0.57); the bunny 0.218
/ 0.201, 0.210 / 0.199, 0.204 / 0.202; the hook 0.194 / 0.187, 0.238 / 0.223, 0.221 / 0.216;
the figurine 0.153 / 0.149, 0.167 / 0.168, 0.155 / 0.152; the torus's charts hold their shape
and it is unchanged (unweighted by the shape's share, the field took it from 0.110 to 0.181).
"""

from __future__ import annotations

import numpy as np

from .faithfulness import LAYERED_KURTOSIS, kurtosis_of, shared_along, signed_residuals
from .kdtree import PointTree

#: The points round a sample that its offset averages, and the width of their Gaussian weights
#: in the atlas's median point spacings: dragon 20k seed 1, Chamfer 0.332 without; 16 points,
#: unweighted by the shape's share: 0.5 spacing 0.338, 1.0 0.320, 1.5 0.315; 32 points, 1.5-2.5
#: spacings 0.317-0.319.
DETAIL_NEIGHBOURS = 16
DETAIL_WIDTH = 1.5
#: Points farther from the chart's mesh than this many noise widths (the residuals' median
#: absolute deviation, scaled to σ) are left out of its field: another surface's (a plate's
#: other face round its rim), not a shape the network smoothed. Sheets at σ 0.2 %, 20k, seeds
#: 0 / 1, Chamfer without the field 0.330 / 0.314, with all points 0.342 / 0.330, with this
#: 0.327 / 0.316; the dragon at seed 1 0.3226 / 0.3229.
DETAIL_INLIERS = 3.0


def _inliers(residuals: np.ndarray) -> np.ndarray:
    """(m,) bool: the ``residuals`` within `DETAIL_INLIERS` robust noise widths of their
    median."""
    off = np.abs(residuals - np.median(residuals))
    return off <= DETAIL_INLIERS * 1.4826 * np.median(off)


class ResidualDetail:
    """One chart's residual field.

    width : the Gaussian weights' width (length units; the atlas passes `DETAIL_WIDTH` point
    spacings); k : points averaged round a sample (`DETAIL_NEIGHBOURS`).
    Fitted: ``points_`` (m, 3) the chart's points, ``residuals_`` (m,) theirs from its mesh,
    signed (positive in front), ``inliers_`` (m,) bool those within `DETAIL_INLIERS` noise
    widths, which the field is made of, ``variance_`` of their residuals and ``shape_`` the part
    of it the shape holds (0 when their neighbours along the mesh share none)."""

    def __init__(self, width: float, k: int = DETAIL_NEIGHBOURS):
        self.width = width
        self.k = k

    def fit(self, mesh, points) -> ResidualDetail:
        """Residuals of ``points`` (m, 3) from ``mesh``, and the part of their variance the
        shape holds."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not (len(points) and len(mesh.vertices)):
            return self.set_fitted(points, np.zeros(len(points)), 0.0, 0.0)
        residuals, normals = signed_residuals(mesh, points, with_normals=True)
        self.set_fitted(points, residuals, 0.0, 0.0)
        inside = self.inliers_
        kept = residuals[inside]
        centred = kept - kept.mean()
        self.variance_ = float(np.mean(centred ** 2))
        if kurtosis_of(kept) >= LAYERED_KURTOSIS:  # (two layers: no shape)
            self.shape_ = max(shared_along(points[inside], centred, normals[inside]), 0.0)
        return self

    def set_fitted(self, points, residuals, variance: float, shape: float) -> ResidualDetail:
        """Take a fitted field (a saved atlas's): the chart's ``points`` (m, 3), their
        ``residuals`` (m,), and the inliers' ``variance`` and ``shape``."""
        self.points_ = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.residuals_ = np.asarray(residuals, dtype=np.float64).reshape(-1)
        self.inliers_ = (_inliers(self.residuals_) if len(self.residuals_)
                         else np.zeros(0, bool))
        self.variance_, self.shape_ = float(variance), float(shape)
        self._tree = self._kept = None
        return self

    def offsets(self, positions, known=None) -> np.ndarray:
        """(q,) how far to move each of ``positions`` (q, 3) along its chart's normal: the
        weighted mean of the residuals of its k nearest points, times shape / (shape + the
        noise variance left in that mean). Zeros when the shape holds none. ``known``: (p, 3)
        positions and their (p,) offsets found before; a row equal to one of them takes its
        offset (a re-mesh moves few of a chart's vertices: the mug's KD queries, 14 ms a
        re-mesh, were most of them for vertices that had not moved)."""
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        k = min(self.k, int(self.inliers_.sum()))
        if self.shape_ <= 0 or k == 0 or self.width <= 0 or len(positions) == 0:
            return np.zeros(len(positions))
        if known is not None and len(known[0]):
            found = rows_among(known[0], positions)
            offsets = np.asarray(known[1], dtype=np.float64)[np.maximum(found, 0)]
            new = found < 0
            if new.any():
                offsets[new] = self.offsets(positions[new])
            return offsets
        if self._tree is None:
            self._tree = PointTree(self.points_[self.inliers_])
            self._kept = self.residuals_[self.inliers_]
        distance, index = self._tree.query(positions, k=k)
        distance, index = distance.reshape(len(positions), k), index.reshape(len(positions), k)
        weights = np.exp(-(distance / self.width) ** 2)
        total = np.maximum(weights.sum(axis=1), 1e-300)
        mean = (weights * self._kept[index]).sum(axis=1) / total
        noise = self.variance_ * (weights ** 2).sum(axis=1) / total ** 2
        return mean * (self.shape_ / (self.shape_ + noise))

    def moved(self, samples, normals, offsets=None) -> np.ndarray:
        """``samples`` (q, 3) moved along their unit ``normals`` (q, 3) by their `offsets`
        (given, or found; the same array when the shape holds none)."""
        if self.shape_ <= 0 or len(samples) == 0:
            return samples
        offsets = self.offsets(samples) if offsets is None else offsets
        return samples + offsets[:, None] * normals

    def __getstate__(self):
        state = dict(vars(self))
        state["_tree"], state["_kept"] = None, None  # built again where they are needed
        return state


def rows_among(rows, queries) -> np.ndarray:
    """(q,) the index in ``rows`` (p, 3) of the row bit for bit equal to each of ``queries``
    (q, 3), −1 where none is."""
    rows, queries = (np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3)
                     for a in (rows, queries))
    if len(rows) == 0:
        return np.full(len(queries), -1)
    keys, asked = (a.view(np.dtype((np.void, 24))).ravel() for a in (rows, queries))
    order = np.argsort(keys, kind="stable")
    at = np.minimum(np.searchsorted(keys[order], asked), len(rows) - 1)
    return np.where(keys[order][at] == asked, order[at], -1)
