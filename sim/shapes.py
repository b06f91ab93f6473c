"""Synthetic surfaces with ground truth: noisy points, their noise-free counterparts, the true 2D
parameters and a dense mesh of the true surface.

Every factory takes ``n_points``, ``noise`` (Gaussian σ as a FRACTION of the true surface's
bounding-box diagonal; 0 gives clean points), ``random_state`` and ``grid`` (False: parameters
uniform in the domain; True: a regular grid with endpoints, e.g. the paper's 6 x 6 and 12 x 12
cones). Scales follow bench/paper_tables.py: S-curve as scikit-learn's ``make_s_curve``, torus
R = 1, r = 0.4, cones of height 1 and base radius 0.5. Pure numpy/trimesh.

The truth meshes are fine enough that their chord error (sagitta) stays below 1e-4 of the
bounding-box diagonal, far under any noise level of interest.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

#: A surface: params (n, 2) -> points (n, 3).
SurfaceFunction = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class SyntheticShape:
    """A sampled synthetic surface. Arrays are read-only.

    points : (n, 3) noisy samples; clean : (n, 3) their noise-free counterparts;
    params : (n, 2) true 2D parameters; truth : dense mesh of the true surface;
    noise_sigma : absolute Gaussian σ of the noise (same unit as the points).
    """

    name: str
    points: np.ndarray
    clean: np.ndarray
    params: np.ndarray
    truth: trimesh.Trimesh
    noise_sigma: float


def s_curve_surface(params):
    """scikit-learn's S-curve: t in [-3π/2, 3π/2], height h in [0, 2]."""
    t, h = params[:, 0], params[:, 1]
    return np.column_stack([np.sin(t), h, np.sign(t) * (np.cos(t) - 1)])


def torus_surface(params, major: float = 1.0, minor: float = 0.4):
    """Torus: θ around the axis, γ around the tube."""
    theta, gamma = params[:, 0], params[:, 1]
    ring = major + minor * np.cos(gamma)
    return np.column_stack([ring * np.cos(theta), ring * np.sin(theta), minor * np.sin(gamma)])


def cone_surface(params, height: float = 1.0, radius: float = 0.5):
    """Cone with its apex at z = height: azimuth φ, s = fraction of the way from apex to base."""
    phi, s = params[:, 0], params[:, 1]
    return np.column_stack([radius * s * np.cos(phi), radius * s * np.sin(phi), height * (1 - s)])


def sphere_cap_surface(params, radius: float = 1.0):
    """Sphere cap around +z; params are azimuthal-equidistant coordinates (arc length, radius
    units) from the pole, so the true parameters are an isometry along radial lines."""
    polar = np.hypot(params[:, 0], params[:, 1]) / radius
    azimuth = np.arctan2(params[:, 1], params[:, 0])
    return radius * np.column_stack(
        [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)]
    )


def saddle_surface(params):
    """Hyperbolic paraboloid z = (x² - y²) / 2 over the parameter square."""
    x, y = params[:, 0], params[:, 1]
    return np.column_stack([x, y, 0.5 * (x**2 - y**2)])


def terrain_surface(params, n_bumps: int = 5, seed: int = 7):
    """Height field: a sum of seeded Gaussian bumps (fixed by ``seed``, not by the sampling)."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-0.8, 0.8, size=(n_bumps, 2))
    heights = rng.uniform(-0.35, 0.35, size=n_bumps)
    widths = rng.uniform(0.25, 0.5, size=n_bumps)
    squared = np.sum((params[:, None, :] - centres[None]) ** 2, axis=-1)
    z = np.sum(heights * np.exp(-squared / (2 * widths**2)), axis=1)
    return np.column_stack([params, z])


def grid_mesh(surface: SurfaceFunction, u_range, v_range, n_u: int, n_v: int) -> trimesh.Trimesh:
    """Triangulate ``surface`` on an n_u x n_v parameter grid; zero-area faces are dropped."""
    u, v = np.meshgrid(np.linspace(*u_range, n_u), np.linspace(*v_range, n_v), indexing="ij")
    vertices = surface(np.column_stack([u.ravel(), v.ravel()]))
    corner = (np.arange(n_u - 1)[:, None] * n_v + np.arange(n_v - 1)[None]).ravel()
    faces = np.concatenate(
        [
            np.column_stack([corner, corner + n_v, corner + 1]),
            np.column_stack([corner + 1, corner + n_v, corner + n_v + 1]),
        ]
    )
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    return trimesh.Trimesh(vertices, faces[mesh.area_faces > 0], process=False)


@dataclass(frozen=True)
class _Domain:
    """A rectangular parameter domain [u0, u1] x [v0, v1]; ``aspect`` is length(u) / length(v)
    on the surface, used to shape grids; ``truth_grid`` the truth mesh's grid size."""

    u_range: tuple[float, float]
    v_range: tuple[float, float]
    aspect: float
    truth_grid: tuple[int, int]


def _grid_shape(n_points: int, aspect: float) -> tuple[int, int]:
    """Factor pair (a, b), a * b = n_points, both >= 2, with a / b closest to ``aspect``."""
    pairs = [(a, n_points // a) for a in range(2, n_points // 2 + 1) if n_points % a == 0]
    if not pairs:
        raise ValueError(f"grid=True needs n_points with a factor pair, got {n_points}")
    return min(pairs, key=lambda p: abs(np.log(p[0] / p[1]) - np.log(aspect)))


def _rectangle_params(domain: _Domain, n_points, grid, rng) -> np.ndarray:
    if grid:
        n_u, n_v = _grid_shape(n_points, domain.aspect)
        u, v = np.meshgrid(
            np.linspace(*domain.u_range, n_u), np.linspace(*domain.v_range, n_v), indexing="ij"
        )
        return np.column_stack([u.ravel(), v.ravel()])
    low = (domain.u_range[0], domain.v_range[0])
    high = (domain.u_range[1], domain.v_range[1])
    return rng.uniform(low, high, size=(n_points, 2))


def _finish(name, surface, params, truth, noise, rng) -> SyntheticShape:
    if noise < 0:
        raise ValueError(f"noise must be >= 0, got {noise}")
    clean = surface(params)
    sigma = float(noise) * float(np.linalg.norm(np.ptp(truth.vertices, axis=0)))
    points = clean + rng.normal(0.0, sigma, size=clean.shape) if sigma > 0 else clean.copy()
    for array in (points, clean, params):
        array.flags.writeable = False
    return SyntheticShape(name, points, clean, params, truth, sigma)


def _rectangle_shape(name, surface, domain, n_points, noise, random_state, grid):
    if n_points < 3:
        raise ValueError(f"a shape needs at least 3 points, got {n_points}")
    rng = np.random.default_rng(random_state)
    params = _rectangle_params(domain, int(n_points), grid, rng)
    truth = grid_mesh(surface, domain.u_range, domain.v_range, *domain.truth_grid)
    return _finish(name, surface, params, truth, noise, rng)


_HALF_PI, _PI = np.pi / 2, np.pi
_DOMAINS = {
    "s_curve": (s_curve_surface, _Domain((-1.5 * _PI, 1.5 * _PI), (0.0, 2.0), 4.7, (600, 60))),
    "torus_quarter": (torus_surface, _Domain((0, _HALF_PI), (0, _HALF_PI), 2.5, (200, 120))),
    "torus_half": (torus_surface, _Domain((0, _PI), (0, _PI), 2.5, (300, 160))),
    "sparse_cone": (cone_surface, _Domain((0, _PI), (0.2, 1.0), 1.0, (300, 20))),
    "dense_cone": (cone_surface, _Domain((0, _PI), (0.2, 1.0), 1.0, (300, 20))),
    "saddle": (saddle_surface, _Domain((-1, 1), (-1, 1), 1.0, (200, 200))),
    "terrain": (terrain_surface, _Domain((-1, 1), (-1, 1), 1.0, (250, 250))),
}


def sphere_cap(n_points=1600, noise=0.0, random_state=None, grid=False, opening=np.pi / 3):
    """Sphere cap of radius 1 and polar half-angle ``opening``; params uniform in the disk of
    radius ``opening`` (grid=True: a sunflower spiral, evenly spread)."""
    if n_points < 3:
        raise ValueError(f"a shape needs at least 3 points, got {n_points}")
    rng = np.random.default_rng(random_state)
    if grid:
        index = np.arange(n_points) + 0.5
        radius, angle = np.sqrt(index / n_points), index * np.pi * (3 - np.sqrt(5))
    else:
        radius, angle = np.sqrt(rng.uniform(size=n_points)), rng.uniform(0, 2 * np.pi, n_points)
    params = opening * np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])

    def polar_grid(polar_azimuth):
        polar, azimuth = polar_azimuth[:, 0], polar_azimuth[:, 1]
        return sphere_cap_surface(
            np.column_stack([polar * np.cos(azimuth), polar * np.sin(azimuth)])
        )

    truth = grid_mesh(polar_grid, (0.0, opening), (0.0, 2 * np.pi), 150, 400)
    return _finish("sphere_cap", sphere_cap_surface, params, truth, noise, rng)


def _factory(name: str, default_points: int, default_grid: bool):
    surface, domain = _DOMAINS[name]

    def make(n_points=default_points, noise=0.0, random_state=None, grid=default_grid):
        return _rectangle_shape(name, surface, domain, n_points, noise, random_state, grid)

    make.__name__ = name
    make.__doc__ = f"{name}: {surface.__doc__.splitlines()[0]} (default {default_points} points)."
    return make


s_curve = _factory("s_curve", 400, False)
torus_quarter = _factory("torus_quarter", 100, False)
torus_half = _factory("torus_half", 100, False)
sparse_cone = _factory("sparse_cone", 36, True)
dense_cone = _factory("dense_cone", 144, True)
saddle = _factory("saddle", 1600, False)
terrain = _factory("terrain", 1600, False)

SHAPES: dict[str, Callable[..., SyntheticShape]] = {
    "s_curve": s_curve,
    "torus_quarter": torus_quarter,
    "torus_half": torus_half,
    "sparse_cone": sparse_cone,
    "dense_cone": dense_cone,
    "sphere_cap": sphere_cap,
    "saddle": saddle,
    "terrain": terrain,
}


def make_shape(name: str, n_points=None, noise=0.0, random_state=None, **options):
    """The shape ``name`` from `SHAPES` (``n_points`` None: the factory's default)."""
    if name not in SHAPES:
        raise ValueError(f"unknown shape {name!r}; choose from {', '.join(SHAPES)}")
    if n_points is not None:
        options["n_points"] = n_points
    return SHAPES[name](noise=noise, random_state=random_state, **options)


__all__ = ["SHAPES", "SyntheticShape", "make_shape", "grid_mesh", *SHAPES]
