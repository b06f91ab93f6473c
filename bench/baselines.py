"""Peers for the quality benchmark: Open3D's screened Poisson and ball pivoting (optional extra)."""

from __future__ import annotations

import functools
import sys

import numpy as np
import trimesh


@functools.cache
def open3d_available() -> bool:
    """Whether Open3D imports; when it is installed but fails (a missing system library, such
    as libusb), says why on stderr once, since the peers' rows then silently go missing."""
    try:
        import open3d  # noqa: F401
    except ImportError as error:
        if getattr(error, "name", None) != "open3d":
            print(f"Open3D is installed but does not import: {error}", file=sys.stderr)
        return False
    return True


def _cloud_with_normals(points: np.ndarray, k: int = 20):
    import open3d as o3d

    points = np.array(points, dtype=np.float64, order="C")  # Open3D needs a writeable copy
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=k))
    cloud.orient_normals_consistent_tangent_plane(k)
    return cloud


def _to_trimesh(mesh) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), process=False)


def poisson(points: np.ndarray, depth: int = 8, density_quantile: float = 0.05) -> trimesh.Trimesh:
    """Screened Poisson (Kazhdan & Hoppe 2013), trimmed of its lowest-density vertices as usual
    for open surfaces (Poisson closes every surface; the trim keeps the part the points support)."""
    import open3d as o3d

    cloud = _cloud_with_normals(points)
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=depth)
    densities = np.asarray(densities)
    mesh.remove_vertices_by_mask(densities < np.quantile(densities, density_quantile))
    # Poisson extrapolates far beyond an open surface: crop to the cloud's bounding box.
    box = o3d.geometry.AxisAlignedBoundingBox(points.min(axis=0), points.max(axis=0))
    return _to_trimesh(mesh.crop(box))


def ball_pivoting(points: np.ndarray) -> trimesh.Trimesh:
    """Ball pivoting (Bernardini et al. 1999) with radii from the mean neighbour spacing."""
    import open3d as o3d

    cloud = _cloud_with_normals(points)
    spacing = float(np.mean(cloud.compute_nearest_neighbor_distance()))
    radii = o3d.utility.DoubleVector([spacing * f for f in (1.0, 1.5, 2.0, 3.0)])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(cloud, radii)
    return _to_trimesh(mesh)
