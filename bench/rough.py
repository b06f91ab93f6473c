"""A real-like rough surface for the speed benches: a height field with detail at several
scales and holes, like a range scan of a weathered face or a relief.

The smooth synthetic shapes of `sim.shapes` let the adaptive search stop at small nets; real
scans do not (a face scan chose (10, 14) and took 27.6 s to search). This surface has
octaves of seeded ridges (wavelengths from the whole patch down to 1/8 of it; amplitude falling
as wavelength^1.2), and three elliptical holes where a scanner saw nothing (occlusion,
specular spots). The truth mesh has the same holes.

    rough_surface(n_points, noise, random_state) -> sim.shapes.SyntheticShape
"""

from __future__ import annotations

import numpy as np

from sim.shapes import SyntheticShape, grid_mesh

#: (centre u, centre v, semi-axis u, semi-axis v) of the holes, in the [-1, 1]² domain.
HOLES = ((-0.45, 0.35, 0.16, 0.10), (0.30, -0.40, 0.12, 0.18), (0.55, 0.50, 0.09, 0.09))


def height(params: np.ndarray, seed: int = 11) -> np.ndarray:
    """(n, 2) → (n, 3): the height field z(u, v) over the plane, fixed by ``seed``."""
    rng = np.random.default_rng(seed)
    u, v = params[:, 0], params[:, 1]
    z = np.zeros(len(params))
    for octave in range(4):  # wavelengths 2, 1, 0.5, 0.25 (patch width 2)
        wavelength = 2.0 / 2**octave
        amplitude = 0.18 * (wavelength / 2.0) ** 1.2
        for _ in range(3):
            angle, phase = rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
            along = u * np.cos(angle) + v * np.sin(angle)
            z += amplitude * np.sin(2 * np.pi * along / wavelength + phase)
    z += 0.25 * np.exp(-((u - 0.1) ** 2 + (v + 0.05) ** 2) / 0.08)  # a nose-like bump
    return np.column_stack([u, v, z])


def _in_holes(params: np.ndarray) -> np.ndarray:
    inside = np.zeros(len(params), dtype=bool)
    for cu, cv, au, av in HOLES:
        inside |= ((params[:, 0] - cu) / au) ** 2 + ((params[:, 1] - cv) / av) ** 2 < 1.0
    return inside


def rough_surface(n_points: int = 1600, noise: float = 0.01,
                  random_state: int | None = None) -> SyntheticShape:
    """``n_points`` samples outside the holes, Gaussian noise σ = ``noise`` × the truth's
    bounding-box diagonal, as `sim.shapes` does."""
    rng = np.random.default_rng(random_state)
    params = np.empty((0, 2))
    while len(params) < n_points:  # rejection sampling: the holes cover ~4 % of the domain
        batch = rng.uniform(-1.0, 1.0, size=(2 * n_points, 2))
        params = np.concatenate([params, batch[~_in_holes(batch)]])
    params = params[:n_points]
    truth = grid_mesh(height, (-1, 1), (-1, 1), 300, 300)
    centres = truth.triangles_center[:, :2]
    truth.update_faces(~_in_holes(centres))
    truth.remove_unreferenced_vertices()
    clean = height(params)
    sigma = float(noise) * float(np.linalg.norm(np.ptp(truth.vertices, axis=0)))
    points = clean + rng.normal(0.0, sigma, size=clean.shape)
    for array in (points, clean, params):
        array.flags.writeable = False
    return SyntheticShape("rough", points, clean, params, truth, sigma)


def make_case(name: str, n_points: int, noise: float, random_state: int | None):
    """A `sim.shapes` shape by name, or "rough" (this module)."""
    if name == "rough":
        return rough_surface(n_points, noise, random_state)
    from sim.shapes import make_shape

    return make_shape(name, n_points, noise=noise, random_state=random_state)
