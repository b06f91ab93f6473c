"""Per-view processing: depth image → points in the object (turntable) frame, cropped, thinned.

Frames: the camera frame is OpenCV's (x right, y down, z forward, mm). The table frame has z up
along the turntable axis and its origin on the axis at plate height (`Calibration`). A point seen
at table angle θ is rotated back by −θ, so every view lands in the one object frame of angle 0.
"""

from __future__ import annotations

import functools
import logging

import numpy as np

from reconstruct.errors import InvalidInputError
from reconstruct.outliers import statistical_outlier_mask

from .calibration import Calibration
from .volume import Cylinder

log = logging.getLogger(__name__)

#: Points (or pixels) of one view at a limit of what the station sees before the object is
#: taken to reach it (`ViewProcessor.limits`): a stray pixel or two does not.
LIMIT_POINTS = 10


@functools.lru_cache(maxsize=8)
def _pixel_rays(height: int, width: int, k: tuple[float, ...]) -> np.ndarray:
    """(H*W, 3) float32 rays with z = 1 for the pixel centres of an image, read-only."""
    fx, skew, cx, _, fy, cy = k[:6]
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    y = (v - cy) / fy
    x = (u - cx - skew * y) / fx
    rays = np.stack([x, y, np.ones_like(x)], axis=-1).reshape(-1, 3).astype(np.float32)
    rays.flags.writeable = False
    return rays


def _check_intrinsics(intrinsics) -> np.ndarray:
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (3, 3) or not (k[0, 0] > 0 and k[1, 1] > 0):
        raise InvalidInputError(f"intrinsics must be (3, 3) with fx, fy > 0, got {k.tolist()}")
    return k


def depth_to_points(depth, intrinsics, pixels: np.ndarray | None = None) -> np.ndarray:
    """Back-project the valid (non-zero) pixels of a depth image.

    depth : (H, W) uint16 (or float) depth along the optical axis, mm; 0 = no measurement.
    intrinsics : (3, 3) pinhole matrix, pixels.
    pixels : optional (H*W,) bool or index array restricting which pixels are used.
    Returns (n, 3) float32 points in the camera frame, mm, in row-major pixel order.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise InvalidInputError(f"depth must be an (H, W) image, got shape {depth.shape}")
    k = _check_intrinsics(intrinsics)
    rays = _pixel_rays(depth.shape[0], depth.shape[1], tuple(k.ravel()[:6]))
    flat = depth.ravel()
    index = np.flatnonzero(flat) if pixels is None else np.asarray(pixels)
    if index.dtype == bool:
        index = np.flatnonzero(index & (flat != 0))
    elif pixels is not None:
        index = index[flat[index] != 0]
    return rays[index] * flat[index].astype(np.float32)[:, None]


def project_points(points, intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection: (n, 3) camera-frame points, mm → ((n, 2) pixel (u, v), (n,) depth mm)."""
    points = np.asarray(points, dtype=np.float64)
    k = _check_intrinsics(intrinsics)
    z = points[:, 2]
    uvw = points @ k.T
    return uvw[:, :2] / z[:, None], z


def voxel_downsample(points, voxel_mm: float) -> np.ndarray:
    """One point per occupied voxel of a grid anchored at the origin: the mean of its points.

    points : (n, 3) float, mm.  Returns (m, 3) float64, m = number of occupied voxels, ordered by
    voxel index (x, then y, then z).
    """
    points = np.asarray(points)
    if not voxel_mm > 0:
        raise InvalidInputError(f"voxel_mm must be > 0, got {voxel_mm}")
    if len(points) == 0:
        return np.empty((0, 3))
    cells = np.floor(points / voxel_mm).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(keys)
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    sums = np.add.reduceat(points[order].astype(np.float64), starts, axis=0)
    counts = np.diff(np.r_[starts, len(points)])
    return sums / counts[:, None]


def _volume_of(volume) -> Cylinder:
    if isinstance(volume, tuple) and not hasattr(volume, "radius_mm"):
        volume = Cylinder(*volume)
    try:
        cylinder = Cylinder(float(volume.radius_mm), float(volume.z_min_mm), float(volume.z_max_mm))
    except AttributeError as exc:
        raise InvalidInputError(f"volume needs radius_mm, z_min_mm, z_max_mm: {exc}") from exc
    if not (cylinder.radius_mm > 0 and cylinder.z_max_mm > cylinder.z_min_mm):
        raise InvalidInputError(f"empty working volume {cylinder}")
    return cylinder


class ViewProcessor:
    """Turn one depth frame into object-frame points: back-project, move, crop, thin, clean.

    calibration : `Calibration` (intrinsics and camera → table transform).
    volume : working cylinder about the axis (`Cylinder` or a tuple of its fields), mm; its
        ``z_min_mm`` should sit a few mm above the plate so the plate is cut away with the
        background.
    voxel_mm : voxel edge of the downsampling grid, mm (None or 0: no downsampling).
    outlier_neighbors, outlier_std : statistical outlier removal (neighbors 0: off).
    """

    def __init__(
        self,
        calibration: Calibration,
        volume,
        voxel_mm: float | None = 2.0,
        outlier_neighbors: int = 8,
        outlier_std: float = 2.5,
    ):
        self.calibration = calibration
        self.volume = volume
        self.voxel_mm = voxel_mm
        self.outlier_neighbors = outlier_neighbors
        self.outlier_std = outlier_std
        self._roi_cache: dict = {}

    def _roi(self, shape: tuple[int, int]) -> tuple[slice, slice, int, int]:
        """Image rows/columns and depth range that can see the cylinder (angle-independent)."""
        key = (shape, self.calibration.intrinsics.tobytes(), tuple(_volume_of(self.volume)))
        if key not in self._roi_cache:
            cyl = _volume_of(self.volume)
            t = np.linspace(0, 2 * np.pi, 73)
            ring = np.stack([np.cos(t), np.sin(t)], axis=1) * cyl.radius_mm
            rim = np.concatenate(
                [np.c_[ring, np.full(len(t), z)] for z in (cyl.z_min_mm, cyl.z_max_mm)]
            )
            rim_cam = rim @ self.calibration.table_to_camera[:3, :3].T
            rim_cam += self.calibration.table_to_camera[:3, 3]
            z = rim_cam[:, 2]
            if z.min() <= 1.0:  # the volume reaches behind the camera: keep the whole image
                roi = (slice(0, shape[0]), slice(0, shape[1]), 1, np.iinfo(np.uint16).max)
            else:
                uv, _ = project_points(rim_cam, self.calibration.intrinsics)
                u0, v0 = np.clip(np.floor(uv.min(axis=0)) - 1, 0, None).astype(int)
                u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 2
                d0, d1 = int(np.floor(z.min())) - 1, int(np.ceil(z.max())) + 1
                roi = (slice(v0, min(v1, shape[0])), slice(u0, min(u1, shape[1])), d0, d1)
            self._roi_cache[key] = roi
        return self._roi_cache[key]

    def back_project(self, depth) -> np.ndarray:
        """(n, 3) float32 camera-frame points of the pixels that can see the working volume."""
        depth = np.asarray(depth)
        if depth.ndim != 2:
            raise InvalidInputError(f"depth must be an (H, W) image, got shape {depth.shape}")
        rows, cols, d0, d1 = self._roi(depth.shape)
        window = depth[rows, cols]
        k = self.calibration.intrinsics.copy()
        k[0, 2] -= cols.start
        k[1, 2] -= rows.start
        return depth_to_points(window, k, pixels=((window >= d0) & (window <= d1)).ravel())

    def to_object(self, points, angle_deg: float) -> np.ndarray:
        """Camera-frame points (n, 3) seen at table angle ``angle_deg`` → object frame, float32."""
        m = self.calibration.table_transform(angle_deg).astype(np.float32)
        return points @ m[:3, :3].T + m[:3, 3]

    def crop(self, points) -> np.ndarray:
        """(n,) bool: the points inside the working cylinder (table or object frame)."""
        cyl = _volume_of(self.volume)
        r2 = points[:, 0] ** 2 + points[:, 1] ** 2
        z = points[:, 2]
        return (r2 <= cyl.radius_mm**2) & (z >= cyl.z_min_mm) & (z <= cyl.z_max_mm)

    def thin(self, points) -> np.ndarray:
        """Voxel-downsampled (m, 3) float64 points (only converted when ``voxel_mm`` is off)."""
        if self.voxel_mm:
            return voxel_downsample(points, self.voxel_mm)
        return np.asarray(points, dtype=np.float64)

    def clean(self, points) -> np.ndarray:
        """The points without statistical outliers (unchanged when ``outlier_neighbors`` is 0)."""
        if not self.outlier_neighbors or len(points) <= self.outlier_neighbors:
            return points
        return points[statistical_outlier_mask(points, self.outlier_neighbors, self.outlier_std)]

    def limits(self, depth, angle_deg: float, points) -> tuple[str, ...]:
        """Which limits of what the station sees the object reaches in one view: "image edge"
        (at least `LIMIT_POINTS` pixels of the image's outermost rows and columns see into the
        working volume), "wall" or "roof" (as many ``points`` (m, 3) of `process` within a
        voxel of the volume's side or top). What lies beyond them is not scanned; the floor,
        which cuts the plate away, is not one."""
        depth = np.asarray(depth)
        cyl = _volume_of(self.volume)
        outer = np.zeros(depth.shape, bool)
        outer[[0, -1], :] = outer[:, [0, -1]] = True
        seen = depth_to_points(depth, self.calibration.intrinsics, pixels=outer.ravel())
        reached = []
        if self.crop(self.to_object(seen, angle_deg)).sum() >= LIMIT_POINTS:
            reached.append("image edge")
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        near = max(self.voxel_mm or 0.0, 1.0)
        radius = np.hypot(points[:, 0], points[:, 1])
        if (radius >= cyl.radius_mm - near).sum() >= LIMIT_POINTS:
            reached.append("wall")
        if (points[:, 2] >= cyl.z_max_mm - near).sum() >= LIMIT_POINTS:
            reached.append("roof")
        return tuple(reached)

    def process(self, depth, angle_deg: float) -> np.ndarray:
        """One frame at table angle ``angle_deg`` → (m, 3) float64 object-frame points, mm."""
        points = self.to_object(self.back_project(depth), angle_deg)
        return self.clean(self.thin(points[self.crop(points)]))
