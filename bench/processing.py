"""Per-view processing speed: depth frame → cropped, thinned, cleaned object-frame points.

Prints the median ms per stage over the frames for `capture.processing.ViewProcessor` and for
Open3D's equivalent pipeline (create_from_depth_image → transform → crop → voxel_down_sample →
remove_statistical_outlier) in the same run, and the ratio. Target: <= 15 ms per 640x400 frame.

Frames come from the simulated camera (`sim://camera?object=vase`) when it is installed, else
from an embree ray cast of a vase on the plate before a wall (same optics), with depth noise.

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.processing --frames 50
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from capture.calibration import Calibration  # noqa: E402
from capture.processing import ViewProcessor  # noqa: E402
from capture.volume import Cylinder  # noqa: E402

K = np.array([[440.0, 0.0, 320.0], [0.0, 440.0, 200.0], [0.0, 0.0, 1.0]])
SHAPE = (400, 640)
TARGET_MS = 15.0


def station_pose(distance=450.0, height=250.0, target_z=80.0) -> np.ndarray:
    """(4, 4) table → camera for a camera on the -y side looking down at the axis."""
    centre = np.array([0.0, -distance, height])
    forward = np.array([0.0, 0.0, target_z]) - centre
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    camera_to_table = np.eye(4)
    camera_to_table[:3, :3] = np.column_stack([right, np.cross(forward, right), forward])
    camera_to_table[:3, 3] = centre
    return np.linalg.inv(camera_to_table)


def raycast_frames(n_frames: int, seed: int = 0):
    """(depths, angles, calibration): a vase on a 150 mm plate before a wall, ray cast by embree."""
    z = np.linspace(0, 160, 60)
    vase = trimesh.creation.revolve(np.c_[45 + 15 * np.sin(np.pi * z / 130), z], sections=96)
    plate = trimesh.creation.cylinder(150, 10, sections=96).apply_translation([0, 0, -5])
    table_to_camera = station_pose()
    v, u = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    rays = rays.reshape(-1, 3)
    rng = np.random.default_rng(seed)
    distinct = []
    for angle in np.linspace(0, 360, 8, endpoint=False):
        turn = trimesh.transformations.rotation_matrix(np.radians(angle), [0, 0, 1])
        scene = trimesh.util.concatenate([vase.copy().apply_transform(turn), plate])
        scene.apply_transform(table_to_camera)
        locations, index, _ = scene.ray.intersects_location(
            np.zeros_like(rays), rays, multiple_hits=False
        )
        depth = np.full(len(rays), 1400.0)  # the wall
        depth[index] = np.minimum(locations[:, 2], 1400.0)
        distinct.append((depth.reshape(SHAPE), angle))
    depths, angles = [], []
    for i in range(n_frames):
        depth, angle = distinct[i % len(distinct)]
        noisy = depth + rng.normal(0, 1, SHAPE) * (depth / 500.0) ** 2
        depths.append(np.round(noisy).astype(np.uint16))
        angles.append(angle)
    return depths, angles, Calibration(K, np.linalg.inv(table_to_camera))


def sim_frames(n_frames: int):
    """(depths, angles, calibration) from the simulated station, or None when it is missing."""
    try:
        from drivers.registry import open_camera, open_turntable
    except ImportError:
        return None
    try:
        camera = open_camera("sim://camera?object=vase&seed=0&station=bench")
    except Exception:
        return None
    with camera, open_turntable("sim://turntable?instant=1&station=bench") as table:
        depths, angles = [], []
        for i in range(n_frames):
            angle = (i * 360.0 / n_frames) % 360
            table.move_to(angle)
            depths.append(camera.grab().depth)
            angles.append(angle)
        return depths, angles, Calibration.from_sim(camera)


def time_ours(processor: ViewProcessor, depths, angles) -> dict[str, list[float]]:
    times: dict[str, list[float]] = {
        k: [] for k in ("back-project", "move+crop", "voxel", "outliers", "total")
    }
    counts = []
    for depth, angle in zip(depths, angles, strict=True):
        t0 = time.perf_counter()
        points = processor.back_project(depth)
        t1 = time.perf_counter()
        points = processor.to_object(points, angle)
        points = points[processor.crop(points)]
        t2 = time.perf_counter()
        points = processor.thin(points)
        t3 = time.perf_counter()
        points = processor.clean(points)
        t4 = time.perf_counter()
        for key, dt in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0), strict=True):
            dt_ms = dt * 1e3
            times[key].append(dt_ms)
        counts.append(len(points))
    times["points"] = counts
    return times


def time_open3d(processor: ViewProcessor, depths, angles) -> dict[str, list[float]] | None:
    try:
        import open3d as o3d
    except ImportError:
        return None
    k = processor.calibration.intrinsics
    intrinsic = o3d.camera.PinholeCameraIntrinsic(
        SHAPE[1], SHAPE[0], k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    )
    times: dict[str, list[float]] = {
        k: [] for k in ("back-project", "move+crop", "voxel", "outliers", "total")
    }
    counts = []
    for depth, angle in zip(depths, angles, strict=True):
        t0 = time.perf_counter()
        cloud = o3d.geometry.PointCloud.create_from_depth_image(
            o3d.geometry.Image(depth), intrinsic, depth_scale=1.0, depth_trunc=65535.0
        )
        t1 = time.perf_counter()
        cloud.transform(processor.calibration.table_transform(angle))
        keep = np.flatnonzero(processor.crop(np.asarray(cloud.points)))
        cloud = cloud.select_by_index(keep)
        t2 = time.perf_counter()
        cloud = cloud.voxel_down_sample(processor.voxel_mm)
        t3 = time.perf_counter()
        cloud, _ = cloud.remove_statistical_outlier(
            processor.outlier_neighbors, processor.outlier_std
        )
        t4 = time.perf_counter()
        for key, dt in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0), strict=True):
            times[key].append(dt * 1e3)
        counts.append(len(cloud.points))
    times["points"] = counts
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--voxel", type=float, default=2.0, help="voxel edge, mm")
    args = parser.parse_args()
    source = sim_frames(args.frames)
    name = "sim://camera?object=vase"
    if source is None:
        source, name = raycast_frames(args.frames), "embree ray cast (sim camera not installed)"
    depths, angles, calibration = source
    processor = ViewProcessor(calibration, Cylinder(150, 3, 300), voxel_mm=args.voxel)
    processor.process(depths[0], angles[0])  # warm the ROI and ray caches
    ours = time_ours(processor, depths, angles)
    peer = time_open3d(processor, depths, angles)
    print(f"frames: {len(depths)} x {SHAPE[1]}x{SHAPE[0]} from {name}; voxel {args.voxel} mm")
    print(f"{'stage':<14}{'ours ms':>10}{'open3d ms':>11}{'ratio':>8}")
    print("-" * 43)
    for key in [k for k in ours if k != "points"]:
        a = float(np.median(ours[key]))
        if peer is None:
            print(f"{key:<14}{a:>10.2f}{'-':>11}{'-':>8}")
        else:
            b = float(np.median(peer[key]))
            print(f"{key:<14}{a:>10.2f}{b:>11.2f}{b / a:>8.2f}")
    points = f"{np.median(ours['points']):.0f}"
    if peer is not None:
        points += f" (open3d {np.median(peer['points']):.0f})"
    print(f"points kept per frame (median): {points}")
    if peer is None:
        print("\nOpen3D not installed (pip install -e '.[bench]'): peer skipped")
    total = float(np.median(ours["total"]))
    verdict = "met" if total <= TARGET_MS else "MISSED"
    print(f"\ntarget <= {TARGET_MS:g} ms per frame: {verdict} ({total:.2f} ms median)")
    print("ratio = open3d / ours (> 1: ours faster); one thread each (OMP_NUM_THREADS=1)")


if __name__ == "__main__":
    main()
