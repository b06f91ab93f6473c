"""Frames per second of the simulated camera at 640×400: our numpy z-buffer against embree ray
casting (``engine=embree``, when embreex is installed) and, as the outside peer, Open3D's
RaycastingScene (when open3d is installed) rendering the same object under the same poses.

    OMP_NUM_THREADS=1 python -m bench.camera_fps [--frames 40] [--threads 1]

Per object: "render" is the object alone (the pose changes every frame, as the table turns);
"grab" is `SimCamera.grab` with the table turning 7° per frame: render, composite with the
plate and wall, stereo noise, uint16 frame. Medians over ``--frames`` frames after 3 warm-ups.
The 50k-face ball is loaded from a mesh file, as a user's object would be; "@250mm" puts the
camera 250 mm from the axis instead of 420 mm, so the ball covers about a third of the image.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import tempfile
import time

import numpy as np
import trimesh

from sim.camera import SimCamera
from sim.render import MeshRenderer, pixel_rays
from sim.station import get_station

TARGET_FPS = 30.0


class Open3DRenderer(MeshRenderer):
    """The peer: Open3D RaycastingScene, one ray per pixel of the object's projected box (the
    same rays as our embree engine), depth and |cos| like `MeshRenderer.render`."""

    engine = "open3d"

    def __init__(self, vertices, faces, cull=True, threads=1):
        super().__init__(vertices, faces, cull)
        import open3d as o3d

        self._o3d, self.threads = o3d, threads
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                 o3d.core.Tensor(self.faces.astype(np.uint32)))

    def render(self, object_to_camera, intrinsics, shape, near=1.0):
        height, width = shape
        k, pose = np.asarray(intrinsics), np.asarray(object_to_camera)
        depth = np.zeros(height * width, np.float32)
        cosine = np.zeros(height * width, np.float32)
        v = self.vertices @ pose[:3, :3].T + pose[:3, 3]
        u, w = k[0, 0] * v[:, 0] / v[:, 2] + k[0, 2], k[1, 1] * v[:, 1] / v[:, 2] + k[1, 2]
        x0, x1 = max(int(np.ceil(u.min())), 0), min(int(np.floor(u.max())), width - 1)
        y0, y1 = max(int(np.ceil(w.min())), 0), min(int(np.floor(w.max())), height - 1)
        rows, cols = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
        pixels = (rows * width + cols).ravel()
        rays = pixel_rays(height, width, k[0, 0], k[1, 1], k[0, 2], k[1, 2])[pixels]
        origin = -pose[:3, :3].T @ pose[:3, 3]
        directions = rays @ pose[:3, :3]
        packed = np.hstack([np.broadcast_to(origin, directions.shape), directions])
        hits = self.scene.cast_rays(self._o3d.core.Tensor(packed.astype(np.float32)),
                                    nthreads=self.threads)
        t = hits["t_hit"].numpy()
        hit = np.isfinite(t)
        face = hits["primitive_ids"].numpy()[hit].astype(np.intp)
        depth[pixels[hit]] = t[hit] * rays[hit, 2]
        cosine[pixels[hit]] = np.abs(np.einsum("ij,ij->i", self.face_normals[face],
                                               directions[hit]))
        return depth.reshape(shape), cosine.reshape(shape)


class Spinner:
    """A station angle source that turns the table by ``step`` degrees at every reading."""

    def __init__(self, step: float = 7.0):
        self.step, self.angle = step, 0.0

    def position_degrees(self) -> float:
        self.angle = (self.angle + self.step) % 360.0
        return self.angle


def median_ms(fn, frames: int) -> float:
    for _ in range(3):
        fn()
    times = []
    for _ in range(frames):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def ball_file(directory: str) -> str:
    """A ~50k-face ball (r = 90 mm) written as a PLY file."""
    path = os.path.join(directory, "ball50k.ply")
    trimesh.creation.uv_sphere(90.0, count=[112, 112]).export(path)
    return path


def measure(name: str, query: str, engines, frames: int, threads: int) -> list[tuple]:
    rows = []
    base = SimCamera(f"sim://camera?{query}&station=bench")
    mesh = base.true_object_mesh()
    turn = np.eye(4)
    for engine in engines:
        if engine == "open3d":
            renderer = Open3DRenderer(mesh.vertices, mesh.faces, threads=threads)
            grab_ms = None
        else:
            camera = SimCamera(f"sim://camera?{query}&station=bench&engine={engine}")
            renderer = camera.renderer
            get_station("bench").angle_source = Spinner()
            with camera:
                grab_ms = median_ms(camera.grab, frames)
        angles = iter(np.arange(10_000) * 7.0)

        def render_once(renderer=renderer, angles=angles):
            a = np.radians(next(angles))
            turn[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
            return renderer.render(base.table_to_camera @ turn, base.intrinsics, base.shape)

        depth, _ = render_once()
        rows.append((name, len(mesh.faces), int((depth > 0).sum()), engine,
                     median_ms(render_once, frames), grab_ms))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--threads", type=int, default=1, help="Open3D ray-casting threads")
    args = parser.parse_args()
    engines = ["numpy"]
    engines += ["embree"] if importlib.util.find_spec("embreex") else []
    engines += ["open3d"] if importlib.util.find_spec("open3d") else []
    with tempfile.TemporaryDirectory() as tmp:
        ball = ball_file(tmp)
        objects = [("vase", "object=vase"), ("bust", "object=bust"), ("box", "object=box"),
                   ("ball50k (file)", f"object={ball}"),
                   ("ball50k @250mm", f"object={ball}&distance=250")]  # fills a third of the image
        rows = [r for name, query in objects for r in measure(name, query, engines, args.frames,
                                                               args.threads)]
    print(f"SimCamera 640×400, medians of {args.frames} frames, OMP_NUM_THREADS="
          f"{os.environ.get('OMP_NUM_THREADS', 'unset')}, Open3D threads={args.threads}")
    print(f"{'object':<15} {'faces':>6} {'obj px':>7} {'engine':<7} {'render ms':>9} "
          f"{'vs numpy':>8} {'grab ms':>8} {'grab fps':>8}  ≥{TARGET_FPS:.0f} fps")
    numpy_ms = {r[0]: r[4] for r in rows if r[3] == "numpy"}
    for name, faces, pixels, engine, render_ms, grab_ms in rows:
        grab = f"{'-':>8} {'-':>8}"
        if grab_ms is not None:
            fps = 1e3 / grab_ms
            grab = f"{grab_ms:8.1f} {fps:8.0f}  {'yes' if fps >= TARGET_FPS else 'NO'}"
        print(f"{name:<15} {faces:>6} {pixels:>7} {engine:<7} {render_ms:9.1f} "
              f"{render_ms / numpy_ms[name]:7.2f}x {grab}")


if __name__ == "__main__":
    main()
