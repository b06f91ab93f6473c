"""Checks on meshes and test clouds shared by the test modules (a helper module: no tests here)."""

import numpy as np


def hits_per_ray(mesh, origins, directions) -> np.ndarray:
    """(r,) how many faces each ray crosses, counted exactly (Möller–Trumbore, every face; a ray
    tracer's "multiple hits" skips a second layer closer than its step)."""
    tri = mesh.triangles
    zlo, zhi = tri[:, :, 2].min(axis=1), tri[:, :, 2].max(axis=1)
    counts = np.zeros(len(origins), dtype=int)
    for start in range(0, len(origins), 64):
        o, d = origins[start : start + 64], directions[start : start + 64]
        top = np.inf if np.any(d[:, 2] > 0) else o[:, 2].max()
        t = tri[(zhi >= o[:, 2].min()) & (zlo <= top)]
        e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
        p = np.cross(d[:, None], e2[None])
        det = np.einsum("rfi,fi->rf", p, e1)
        s = o[:, None] - t[None, :, 0]
        u = np.einsum("rfi,rfi->rf", s, p) / det
        q = np.cross(s, e1[None])
        v = np.einsum("ri,rfi->rf", d, q) / det
        dist = np.einsum("rfi,fi->rf", q, e2) / det
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (dist > 0) & (np.abs(det) > 1e-12)
        counts[start : start + 64] = hit.sum(axis=1)
    return counts


def side_rays(heights, angles_deg):
    """Horizontal rays from the axis outwards at every (height, angle)."""
    zz, aa = np.meshgrid(heights, np.radians(angles_deg), indexing="ij")
    origins = np.c_[np.zeros(zz.size), np.zeros(zz.size), zz.ravel()]
    return origins, np.c_[np.cos(aa.ravel()), np.sin(aa.ravel()), np.zeros(zz.size)]


def sphere_cloud(n=1500, sigma=0.01, seed=0) -> np.ndarray:
    """(n, 3) points on the unit sphere with Gaussian noise of ``sigma`` of the diagonal."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return direction + rng.normal(0, sigma * 2 * np.sqrt(3), (n, 3))
