"""Estimating the station calibration: the turntable axis from views of a target (as Horus and
FabScan do).

A target whose features trace circles about the axis is captured at several table angles: the
"dumbbell" (two spheres of known radius on a bar, symmetric about the axis, on a post). Per view
the spheres are found (RANSAC with centre hypotheses from point normals, then a least-squares fit
of the centre with the radius fixed); all centres lie on one circle. A plane fit (SVD) of the
centres gives the axis direction, a circle fit in that plane (Kasa, then `least_squares`) the axis
point, and a plane fit on the plate (or the target's known height when no plate is seen) the
plate height. The sense of rotation comes from how the centres' phases follow the table angles.

Frames: camera frame as OpenCV (x right, y down, z forward), mm. Table frame: z up along the axis,
origin where the axis meets the plate, y along the camera's viewing direction projected on the
plate (away from the camera), x = y × z.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import trimesh
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from .calibration import Calibration, CalibrationError
from .processing import depth_to_points, voxel_downsample

log = logging.getLogger(__name__)


# --- geometric fits -------------------------------------------------------------------------


def fit_plane(points) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane of (n, 3) points → (centroid (3,), unit normal (3,)) by SVD."""
    points = np.asarray(points, dtype=np.float64)
    centroid = points.mean(axis=0)
    return centroid, np.linalg.svd(points - centroid, full_matrices=False)[2][2]


def fit_circle_3d(points) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Circle through (n >= 3, 3) points → (centre (3,), unit normal (3,), radius, (n,) residuals).

    Plane by SVD, Kasa's algebraic fit in the plane, then `least_squares` on the distances to the
    circle (in-plane and out-of-plane) with centre, normal and radius free. Same units as input.
    """
    points = np.asarray(points, dtype=np.float64)
    centroid, normal = fit_plane(points)
    e1 = np.linalg.svd(points - centroid, full_matrices=False)[2][0]
    e2 = np.cross(normal, e1)
    uv = np.column_stack([(points - centroid) @ e1, (points - centroid) @ e2])
    a = np.column_stack([2 * uv, np.ones(len(uv))])
    (cu, cv, c0), *_ = np.linalg.lstsq(a, (uv**2).sum(axis=1), rcond=None)
    centre0 = centroid + cu * e1 + cv * e2
    radius0 = np.sqrt(max(c0 + cu**2 + cv**2, 0.0))

    def unpack(q):
        n = normal + q[3] * e1 + q[4] * e2
        return q[:3], n / np.linalg.norm(n), q[5]

    def residuals(q):
        centre, n, radius = unpack(q)
        d = points - centre
        axial = d @ n
        radial = np.linalg.norm(d - axial[:, None] * n, axis=1) - radius
        return np.concatenate([axial, radial])

    fit = least_squares(residuals, np.r_[centre0, 0.0, 0.0, radius0], method="lm")
    centre, n, radius = unpack(fit.x)
    r = fit.fun.reshape(2, -1)
    return centre, n, float(radius), np.hypot(r[0], r[1])


def estimate_normals(points, at=None, n_neighbors: int = 16, tree=None) -> np.ndarray:
    """(m, 3) unit normals by local PCA at ``points[at]`` (all by default), facing the camera
    at the origin. points : (n, 3); at : optional index array of the m points wanted."""
    query = points if at is None else points[at]
    tree = cKDTree(points) if tree is None else tree
    _, idx = tree.query(query, k=min(n_neighbors, len(points)))
    local = points[idx] - points[idx].mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))[1][:, :, 0]
    flip = np.einsum("ij,ij->i", normals, query) > 0
    normals[flip] *= -1
    return normals


def fit_sphere_centre(points, radius: float, centre0) -> np.ndarray:
    """Least-squares centre (3,) of a sphere of known ``radius`` through (n, 3) points."""
    fit = least_squares(
        lambda c: np.linalg.norm(points - c, axis=1) - radius, centre0, loss="soft_l1", f_scale=1
    )
    return fit.x


def find_spheres(
    points, radius: float, count: int = 2, tol: float = 2.0, min_inliers: int = 60, rng=None
) -> list[np.ndarray]:
    """Up to ``count`` sphere centres (3,) of known ``radius`` in a camera-frame cloud (n, 3), mm.

    RANSAC: each hypothesis is a point moved ``radius`` against its normal. It scores the points
    within ``tol`` of its sphere minus three times the points inside it (a visible sphere has
    nothing inside, so spheres cutting through a plane lose); the best is refined with the radius
    fixed and its points removed before the next search. A sphere needs ``min_inliers`` points,
    at least a third of the first sphere's count, and almost no points inside.
    """
    rng = np.random.default_rng(rng)
    points = np.asarray(points, dtype=np.float64)
    tree = cKDTree(points)
    remaining = np.ones(len(points), dtype=bool)
    centres: list[np.ndarray] = []
    first = 0
    sub = points[rng.choice(len(points), size=min(4000, len(points)), replace=False)]
    for _ in range(count):
        idx = np.flatnonzero(remaining)
        if len(idx) < min_inliers:
            break
        seeds = rng.choice(idx, size=min(400, len(idx)), replace=False)
        hypotheses = points[seeds] - radius * estimate_normals(points, seeds, tree=tree)
        dist = np.linalg.norm(sub[None, :, :] - hypotheses[:, None, :], axis=2)
        score = (np.abs(dist - radius) < tol).sum(axis=1) - 3 * (dist < radius - 2 * tol).sum(1)
        best = hypotheses[np.argmax(score)]
        for _ in range(3):
            near = np.abs(np.linalg.norm(points[idx] - best, axis=1) - radius) < tol
            if near.sum() < 4:
                break
            best = fit_sphere_centre(points[idx][near], radius, best)
        dist = np.linalg.norm(points - best, axis=1)
        n_in = int((remaining & (np.abs(dist - radius) < tol)).sum())
        n_inside = int((dist < radius - 2 * tol).sum())
        log.debug("sphere candidate %s: %d inliers, %d inside", best.round(1), n_in, n_inside)
        if n_in < max(min_inliers, first // 3) or n_inside > 0.1 * n_in:
            break
        first = first or n_in
        centres.append(best)
        remaining &= dist > radius + 2 * tol
    return centres


# --- the target and the axis ----------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class DumbbellTarget:
    """Two spheres on a bar, symmetric about the axis, held up by a post on the axis (mm).

    The spheres' centres sit at (±half_span_mm, 0, centre_height_mm) in the table frame.
    """

    sphere_radius_mm: float = 20.0
    half_span_mm: float = 70.0
    centre_height_mm: float = 90.0
    bar_radius_mm: float = 4.0

    def mesh(self) -> trimesh.Trimesh:
        """The target as one mesh standing on z = 0 (parts concatenated, not booleaned)."""
        r, span, h, rb = (
            self.sphere_radius_mm,
            self.half_span_mm,
            self.centre_height_mm,
            self.bar_radius_mm,
        )
        parts = [
            trimesh.creation.icosphere(4, r).apply_translation([x, 0, h]) for x in (-span, span)
        ]
        bar = trimesh.creation.cylinder(rb, 2 * span, sections=32)
        bar.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        parts.append(bar.apply_translation([0, 0, h]))
        parts.append(trimesh.creation.cylinder(rb, h, sections=32).apply_translation([0, 0, h / 2]))
        return trimesh.util.concatenate(parts)


def estimate_axis(centres, angles_deg, up=(0.0, -1.0, 0.0)):
    """Axis from feature centres that trace one circle about it.

    centres : (n, 3) camera frame, mm; angles_deg : (n,) table angle of each centre.
    up : rough up direction in the camera frame (default: image up) to orient the axis.
    Returns (point on the axis in the circles' plane (3,), unit direction up (3,), rotation_sign,
    (n,) residuals mm).
    """
    centres = np.asarray(centres, dtype=np.float64)
    angles = np.radians(np.asarray(angles_deg, dtype=np.float64))
    if len(centres) < 3:
        raise CalibrationError(f"need >= 3 feature centres for the axis, got {len(centres)}")
    centre, normal, _, residuals = fit_circle_3d(centres)
    if normal @ np.asarray(up) < 0:
        normal = -normal
    e1 = np.linalg.svd(centres - centre, full_matrices=False)[2][0]
    e1 -= (e1 @ normal) * normal
    e1 /= np.linalg.norm(e1)
    d = centres - centre
    phase = np.arctan2(d @ np.cross(normal, e1), d @ e1)
    # Two symmetric features are 180° apart: compare phases modulo 180° (doubled angles).
    score = {s: abs(np.mean(np.exp(2j * (phase - s * angles)))) for s in (1, -1)}
    if abs(score[1] - score[-1]) < 0.2:
        raise CalibrationError("the table angles cannot tell the direction of rotation")
    return centre, normal, max(score, key=score.get), residuals


def _plate_offset(cloud, centre, normal, target: DumbbellTarget, tol: float) -> float | None:
    """Signed distance along the axis from ``centre`` to the plate, or None if too few points."""
    d = cloud - centre
    s = d @ normal
    rho = np.linalg.norm(d - s[:, None] * normal, axis=1)
    h = target.centre_height_mm
    near = (np.abs(s + h) < 25) & (rho > target.bar_radius_mm + 3 * tol)
    near &= rho < target.half_span_mm + 2 * target.sphere_radius_mm
    if near.sum() < 100:
        return None
    hist, edges = np.histogram(s[near], bins=np.arange(-h - 25, -h + 25 + tol, tol))
    mode = edges[np.argmax(hist)] + tol / 2
    plate = near & (np.abs(s - mode) < 2 * tol)
    if plate.sum() < 100:
        return None
    q, m = fit_plane(cloud[plate])
    return float((q - centre) @ m / (normal @ m))


def calibrate_from_views(
    depths,
    angles_deg,
    intrinsics,
    target: DumbbellTarget | None = None,
    voxel_mm: float = 1.5,
    tol_mm: float = 2.0,
    max_range_mm: float = 1500.0,
    min_views: int = 4,
    random_state=0,
) -> Calibration:
    """Calibrate from depth images (H, W) uint16 mm of the target at table angles (degrees)."""
    target = target or DumbbellTarget()
    rng = np.random.default_rng(random_state)
    centres, angles, clouds = [], [], []
    for depth, angle in zip(depths, angles_deg, strict=True):
        cloud = depth_to_points(depth, intrinsics)
        cloud = voxel_downsample(cloud[cloud[:, 2] < max_range_mm], voxel_mm)
        found = (
            find_spheres(cloud, target.sphere_radius_mm, 2, tol_mm, rng=rng) if len(cloud) else []
        )
        log.info("angle %.1f°: %d sphere(s) found in %d points", angle, len(found), len(cloud))
        centres += found
        angles += [angle] * len(found)
        clouds.append(cloud)
    n_views = len(set(angles))
    if n_views < min_views:
        raise CalibrationError(
            f"target spheres found at only {n_views} of {len(clouds)} angles (need {min_views})"
        )
    centres, angles = np.array(centres), np.array(angles)
    for _ in range(5):  # drop misdetections far off the circle, then refit
        centre, normal, sign, residuals = estimate_axis(centres, angles)
        keep = residuals <= max(3 * np.median(residuals), tol_mm)
        if keep.all() or keep.sum() < 3:
            break
        log.info("dropping %d centre(s) off the axis circle", int((~keep).sum()))
        centres, angles = centres[keep], angles[keep]
    rms = float(np.sqrt(np.mean(residuals**2)))
    offsets = [_plate_offset(c, centre, normal, target, tol_mm) for c in clouds]
    offsets = [o for o in offsets if o is not None]
    if offsets:
        offset = float(np.median(offsets))
        log.info(
            "plate %.2f mm below the sphere centres (target says %.2f)",
            -offset,
            target.centre_height_mm,
        )
    else:
        offset = -target.centre_height_mm
        log.info("plate not seen: using the target's centre height %.2f mm", -offset)
    log.info("axis fit from %d centres: rms %.3f mm, rotation sign %+d", len(centres), rms, sign)
    return Calibration.from_axis(intrinsics, centre + offset * normal, normal, sign, rms)


def calibrate(
    camera, turntable, angles=tuple(range(0, 360, 30)), target: DumbbellTarget | None = None, **kw
) -> Calibration:
    """Capture the target at each table angle (degrees), then `calibrate_from_views`."""
    depths = []
    for angle in angles:
        turntable.move_to(angle)
        depths.append(camera.grab().depth)
    return calibrate_from_views(depths, angles, camera.intrinsics, target, **kw)
