"""A scan's mesh against the simulated object's true surface, on the part the views could see.

The visible surface: area-uniform samples of the true mesh that at least one view saw — inside
the image, facing the camera (incidence cosine above ``min_cos``), not hidden by the object
itself (a ray to the camera centre), and inside the working volume. Completeness is the share
of those within τ = 1 % of the object's size (bounding-box diagonal) of the mesh; accuracy and
the denoise ratio compare RMS distances to the truth of mesh samples and of the input points.
"""

from __future__ import annotations

import numpy as np
import trimesh

from reconstruct.metrics import distance_to_surface, sample_surface

from .calibration import Calibration
from .processing import project_points
from .volume import Cylinder

TAU_FRACTION = 0.01


def visible_samples(truth: trimesh.Trimesh, calibration: Calibration, angles_deg, image_shape,
                    volume: Cylinder, n_samples: int = 20_000, min_cos: float = 0.1,
                    random_state: int = 0) -> np.ndarray:
    """(v, 3) samples of ``truth`` (object frame, mm) seen by at least one view."""
    points, faces = trimesh.sample.sample_surface(truth, n_samples, seed=random_state)
    normals = truth.face_normals[faces]
    radius = np.hypot(points[:, 0], points[:, 1])
    inside = (radius <= volume.radius_mm) & (points[:, 2] >= volume.z_min_mm)
    inside &= points[:, 2] <= volume.z_max_mm
    seen = np.zeros(len(points), dtype=bool)
    height, width = image_shape
    lift = 1e-3 * float(np.linalg.norm(np.ptp(truth.vertices, axis=0)))
    for angle in angles_deg:
        object_from_camera = calibration.table_transform(angle)
        centre = object_from_camera[:3, 3]
        to_camera = centre - points
        distance = np.linalg.norm(to_camera, axis=1)
        facing = np.einsum("ij,ij->i", normals, to_camera) > min_cos * distance
        camera_from_object = np.linalg.inv(object_from_camera)
        cam = points @ camera_from_object[:3, :3].T + camera_from_object[:3, 3]
        uv, z = project_points(cam, calibration.intrinsics)
        framed = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0)
        framed &= uv[:, 1] < height
        candidates = np.flatnonzero(facing & framed & inside & ~seen)
        if len(candidates) == 0:
            continue
        origins = points[candidates] + lift * normals[candidates]
        directions = to_camera[candidates] / distance[candidates, None]
        hidden = truth.ray.intersects_any(origins, directions)
        seen[candidates[~hidden]] = True
    return points[seen]


def surface_quality(mesh: trimesh.Trimesh, fused_points, truth: trimesh.Trimesh,
                    visible: np.ndarray, raw_points=None, n_samples: int = 20_000) -> dict:
    """Figures of ``mesh`` against ``truth``: completeness of ``visible`` within τ, accuracy,
    RMS distances and denoise ratios (mesh RMS / input RMS; < 1 means noise was removed). The
    input points' RMS distances are estimated on a random ``n_samples`` of them (to ~0.5 %):
    the exact distances of every raw point of a 36-view scan (~120k) took 10 of the main job's
    43 s."""
    size = float(np.linalg.norm(np.ptp(truth.vertices, axis=0)))
    tau = TAU_FRACTION * size
    to_mesh = distance_to_surface(mesh, visible)
    mesh_samples = sample_surface(mesh, n_samples, random_state=0)
    to_truth = distance_to_surface(truth, mesh_samples)
    fused = distance_to_surface(truth, _subset(fused_points, n_samples))
    rms = float(np.sqrt(np.mean(to_truth**2)))
    fused_rms = float(np.sqrt(np.mean(fused**2)))
    figures = {
        "object_size_mm": size,
        "tau_mm": tau,
        "visible_samples": len(visible),
        "completeness_visible": float(np.mean(to_mesh <= tau)),
        "completeness_mean_mm": float(to_mesh.mean()),
        "precision": float(np.mean(to_truth <= tau)),
        "accuracy_mean_mm": float(to_truth.mean()),
        "mesh_rms_mm": rms,
        "fused_rms_mm": fused_rms,
        "denoise_ratio": rms / fused_rms if fused_rms > 0 else float("nan"),
    }
    if raw_points is not None and len(raw_points):
        raw = distance_to_surface(truth, _subset(raw_points, n_samples))
        raw_rms = float(np.sqrt(np.mean(raw**2)))
        figures["raw_rms_mm"] = raw_rms
        figures["denoise_ratio_raw"] = rms / raw_rms if raw_rms > 0 else float("nan")
    return figures


def _subset(points, n: int) -> np.ndarray:
    """(≤ n, 3) float64: ``points``, or a seeded random n of them."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) <= n:
        return points
    return points[np.sort(np.random.default_rng(0).choice(len(points), n, replace=False))]
