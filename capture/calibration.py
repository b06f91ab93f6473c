"""Station calibration: where the turntable axis is in the camera frame (as Horus and FabScan do).

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
import json
import logging
from pathlib import Path

import numpy as np
import trimesh
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from .processing import depth_to_points, voxel_downsample

log = logging.getLogger(__name__)

FORMAT = "scanstation-calibration/1"


class CalibrationError(ValueError):
    """A calibration that cannot be estimated, loaded or used (message names the cause)."""


def _rigid_inverse(m: np.ndarray) -> np.ndarray:
    inv = np.eye(4)
    inv[:3, :3] = m[:3, :3].T
    inv[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return inv


def _rotation_z(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


@dataclasses.dataclass(frozen=True, eq=False)
class Calibration:
    """Intrinsics and the camera → table rigid transform of one station.

    intrinsics : (3, 3) pinhole matrix, pixels.  camera_to_table : (4, 4) rigid transform, mm.
    rotation_sign : +1 when a positive table angle turns the plate counter-clockwise seen from
        above (right-handed about the table's z), else -1.
    residual_mm : RMS residual of the axis circle fit (0 for a known truth).
    """

    intrinsics: np.ndarray
    camera_to_table: np.ndarray
    rotation_sign: int = 1
    residual_mm: float = 0.0

    def __post_init__(self):
        k = np.array(self.intrinsics, dtype=np.float64)
        m = np.array(self.camera_to_table, dtype=np.float64)
        if (
            k.shape != (3, 3)
            or not (k[0, 0] > 0 and k[1, 1] > 0)
            or not np.allclose(k[2], [0, 0, 1])
        ):
            raise CalibrationError(f"intrinsics must be a (3, 3) pinhole matrix, got {k.tolist()}")
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise CalibrationError(f"camera_to_table must be a finite (4, 4) matrix, got {m.shape}")
        r = m[:3, :3]
        rigid = np.allclose(r @ r.T, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0
        if not rigid or not np.allclose(m[3], [0, 0, 0, 1]):
            raise CalibrationError("camera_to_table is not a rigid transform (rotation + shift)")
        if self.rotation_sign not in (1, -1):
            raise CalibrationError(f"rotation_sign must be +1 or -1, got {self.rotation_sign}")
        for name, value in (("intrinsics", k), ("camera_to_table", m)):
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        object.__setattr__(self, "rotation_sign", int(self.rotation_sign))
        object.__setattr__(self, "residual_mm", float(self.residual_mm))

    @property
    def table_to_camera(self) -> np.ndarray:
        """(4, 4) inverse of ``camera_to_table``."""
        return _rigid_inverse(self.camera_to_table)

    @property
    def axis_origin(self) -> np.ndarray:
        """(3,) where the axis meets the plate, camera frame, mm."""
        return self.table_to_camera[:3, 3]

    @property
    def axis_direction(self) -> np.ndarray:
        """(3,) unit vector up the axis, camera frame."""
        return self.table_to_camera[:3, 2]

    def table_transform(self, angle_deg: float) -> np.ndarray:
        """(4, 4) camera frame at table angle ``angle_deg`` → object frame (the table at 0°)."""
        return _rotation_z(-self.rotation_sign * angle_deg) @ self.camera_to_table

    @classmethod
    def from_axis(cls, intrinsics, axis_origin, axis_direction, rotation_sign=1, residual_mm=0.0):
        """Build from the axis in camera coordinates (origin on the plate, direction up)."""
        z = np.asarray(axis_direction, dtype=np.float64)
        z = z / np.linalg.norm(z)
        forward = np.array([0.0, 0.0, 1.0]) - z[2] * z
        if np.linalg.norm(forward) < 1e-6:  # looking straight along the axis
            forward = np.array([0.0, 1.0, 0.0]) - z[1] * z
        y = forward / np.linalg.norm(forward)
        x = np.cross(y, z)
        table_to_camera = np.eye(4)
        table_to_camera[:3, :3] = np.column_stack([x, y, z])
        table_to_camera[:3, 3] = axis_origin
        return cls(intrinsics, _rigid_inverse(table_to_camera), rotation_sign, residual_mm)

    @classmethod
    def from_sim(cls, camera) -> Calibration:
        """The true calibration of a simulated camera (from its ground-truth pose).

        Reads ``camera.camera_to_table`` (4, 4) (or ``camera.true_pose``, taken as camera →
        table) and ``camera.rotation_sign`` (default +1).
        """
        pose = getattr(camera, "camera_to_table", None)
        if pose is None:
            pose = getattr(camera, "true_pose", None)
        if pose is None:
            raise CalibrationError(f"{type(camera).__name__} exposes no true pose")
        return cls(camera.intrinsics, np.asarray(pose), getattr(camera, "rotation_sign", 1))

    def to_json(self) -> str:
        return json.dumps(
            {
                "format": FORMAT,
                "intrinsics": self.intrinsics.tolist(),
                "camera_to_table": self.camera_to_table.tolist(),
                "rotation_sign": self.rotation_sign,
                "residual_mm": self.residual_mm,
            },
            indent=1,
        )

    @classmethod
    def from_json(cls, text: str) -> Calibration:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"calibration is not valid JSON: {exc}") from exc
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise CalibrationError(f"not a calibration file (expected format {FORMAT!r})")
        missing = [k for k in ("intrinsics", "camera_to_table") if k not in data]
        if missing:
            raise CalibrationError(f"calibration lacks {', '.join(missing)}")
        try:
            k = np.array(data["intrinsics"], dtype=np.float64)
            m = np.array(data["camera_to_table"], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"calibration matrices are not numeric: {exc}") from exc
        return cls(k, m, data.get("rotation_sign", 1), data.get("residual_mm", 0.0))

    def save(self, path) -> None:
        Path(path).write_text(self.to_json())

    @classmethod
    def load(cls, path) -> Calibration:
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise CalibrationError(f"cannot read calibration {path}: {exc.strerror}") from exc
        return cls.from_json(text)


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
