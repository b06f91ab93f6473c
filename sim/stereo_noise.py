"""OAK-D-like stereo depth noise applied to an ideal depth image.

Stereo measures disparity d = f·B/z (pixels). Matching error is roughly constant in disparity
(σ of a fraction of a pixel), so depth error grows with z²; subpixel disparity is quantised
(1/8 px on the OAK with subpixel on). Matching fails where the surface is seen at a grazing
angle, where the second camera cannot see the point (the occlusion "shadow" beside a foreground
edge, removed by the left-right check), at some silhouette-edge pixels, and outside the range.
The reference camera is the one rendering the image; its partner sits ``baseline_mm`` to its
right (+x).
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class StereoNoise:
    """Parameters of the noise model (OAK-D defaults); ``apply`` adds it to a depth image."""

    baseline_mm: float = 75.0
    sigma_px: float = 0.08  # disparity error (standard deviation), pixels
    subpixel_levels: int = 8  # disparity quantised to 1/levels px
    min_cos: float = 0.2  # matching fails below this |cos| between normal and viewing ray
    occlusion_tol_px: float = 0.5  # how far behind a nearer surface a pixel must be to be hidden
    edge_jump: float = 0.03  # relative depth jump between neighbours that marks a silhouette edge
    edge_dropout: float = 0.5  # probability that a silhouette-edge pixel is missing
    min_mm: float = 200.0
    max_mm: float = 5000.0

    def __post_init__(self):
        if not (self.baseline_mm > 0 and self.sigma_px >= 0 and self.subpixel_levels >= 1):
            raise ValueError(f"invalid stereo noise parameters: {self}")

    def apply(self, depth, cosine, fx: float, rng: np.random.Generator) -> np.ndarray:
        """Noisy depth (H, W) uint16 mm (0 = missing) from ideal depth (H, W) float mm
        (0 = nothing) and |cosine| (H, W) of the incidence; ``fx`` focal length in pixels."""
        z = np.asarray(depth, dtype=np.float64)
        fb = fx * self.baseline_mm
        disparity = np.divide(fb, z, out=np.zeros_like(z), where=z > 0)
        valid = (z > 0) & (np.asarray(cosine) >= self.min_cos)
        valid &= ~occluded_in_partner(disparity, self.occlusion_tol_px)
        edges = np.flatnonzero(silhouette_edges(z, self.edge_jump))
        valid.ravel()[edges[rng.random(len(edges)) < self.edge_dropout]] = False

        at = np.flatnonzero(valid)
        measured = disparity.ravel()[at]
        if self.sigma_px > 0:
            measured = measured + self.sigma_px * rng.standard_normal(len(at))
        measured = np.round(measured * self.subpixel_levels) / self.subpixel_levels
        with np.errstate(divide="ignore"):
            noisy = np.where(measured > 0, fb / measured, 0.0)
        noisy = np.where((noisy >= self.min_mm) & (noisy <= self.max_mm), np.round(noisy), 0.0)
        out = np.zeros(z.size, np.uint16)
        out[at] = noisy
        return out.reshape(z.shape)

    def depth_sigma_mm(self, z_mm, fx: float):
        """Expected depth standard deviation (mm) at depth ``z_mm``: σ_d · z² / (f·B)."""
        return self.sigma_px * np.asarray(z_mm, dtype=np.float64) ** 2 / (fx * self.baseline_mm)


def occluded_in_partner(disparity, tol_px: float = 0.5) -> np.ndarray:
    """(H, W) bool: pixels the partner camera (to the right) cannot see.

    A pixel u with disparity d appears at u − d in the partner image; it is hidden when a pixel
    further right lands at or left of that spot (a nearer surface covers it): along each row,
    u − d(u) > min over u' > u of (u' − d(u')) + tol. Pixels without depth never hide others.
    """
    d = np.asarray(disparity, dtype=np.float64)
    shifted = np.arange(d.shape[1], dtype=np.float64)[None, :] - d
    ahead_min = np.minimum.accumulate(shifted[:, ::-1], axis=1)[:, ::-1]
    ahead_min = np.concatenate([ahead_min[:, 1:], np.full((d.shape[0], 1), np.inf)], axis=1)
    return (shifted > ahead_min + tol_px) & (d > 0)


def silhouette_edges(depth, jump: float) -> np.ndarray:
    """(H, W) bool: pixels with depth whose 4-neighbourhood has no depth or a relative depth
    jump above ``jump``."""
    z = np.asarray(depth, dtype=np.float64)
    edge = np.zeros(z.shape, bool)
    limit = jump * np.maximum(z, 1.0)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        za, zb = z[tuple(a)], z[tuple(b)]
        step = ((za == 0) != (zb == 0)) | (np.abs(za - zb) > np.minimum(limit[tuple(a)],
                                                                         limit[tuple(b)]))
        edge[tuple(a)] |= step
        edge[tuple(b)] |= step
    return edge & (z > 0)
