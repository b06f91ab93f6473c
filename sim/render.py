"""Depth images of triangle meshes through a pinhole camera: a vectorised numpy z-buffer (the
reference) and, behind the same interface, embree ray casting when ``embreex`` is installed.

The z-buffer culls faces (back-facing, behind the near plane, no pixel centre in their box),
groups the rest by the power-of-two size of their pixel box and rasterises each group as one
dense (faces, rows, cols) block by broadcasting barycentric edge functions — no per-pixel
gathers. The nearest surface per pixel is kept with ``np.maximum.at`` on 1/z, which is linear in
the image, so depth is interpolated perspective-correctly. Faces reaching behind the near plane
are dropped, not clipped (simulated scenes stay well in front of the camera). Camera axes
follow OpenCV (x right, y down, z forward); lengths are in the vertices' unit (mm here).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

_BLOCK_CELLS = 1 << 21  # candidate pixels per broadcast block (bounds temporary memory)
_EDGE_EPS = 1e-7  # barycentric tolerance: pixel centres on shared edges go to both faces
ENGINES = ("numpy", "embree")


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) camera → world transform of a camera at ``eye`` (3,) looking at ``target`` (3,)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([right, np.cross(forward, right), forward])
    pose[:3, 3] = eye
    return pose


def intrinsics_for(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """(3, 3) pinhole matrix with square pixels and the principal point at the image centre."""
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


@functools.lru_cache(maxsize=8)
def pixel_rays(height: int, width: int, fx: float, fy: float, cx: float, cy: float):
    """(H*W, 3) unit viewing rays through the pixel centres, camera frame (read-only)."""
    v, u = np.mgrid[0:height, 0:width]
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones((height, width))], -1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays.flags.writeable = False
    return rays


class _Faces(NamedTuple):
    """Per-face rasterisation set-up (all (k,)): barycentrics l1, l2 at the box corner (x0, y0)
    and their steps per pixel, the box size, and 1/z at corner 0 plus its steps along l1, l2."""

    l1: np.ndarray
    l2: np.ndarray
    a1: np.ndarray
    b1: np.ndarray
    a2: np.ndarray
    b2: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    bw: np.ndarray
    bh: np.ndarray
    q0: np.ndarray
    dq1: np.ndarray
    dq2: np.ndarray


class MeshRenderer:
    """Renders one mesh under changing poses; per-mesh arrays are prepared once.

    vertices : (n, 3) float, object frame.  faces : (m, 3) int.
    cull : drop back faces (needs a closed mesh with outward, consistent winding).
    """

    engine = "numpy"

    def __init__(self, vertices, faces, cull: bool = True):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.intp)
        tri = self.vertices[self.faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        self.face_normals = np.divide(
            normals, length, out=np.zeros_like(normals), where=length > 0
        )  # (m, 3) unit, object frame
        self._face_offsets = np.einsum("ij,ij->i", self.face_normals, tri[:, 0])  # n·v0, (m,)
        self.cull = cull

    def render(self, object_to_camera, intrinsics, shape, near: float = 1.0):
        """Depth (H, W) float32 (0 = no surface) and the |cosine| (H, W) float32 between the
        surface normal and the viewing ray (0 where empty) of the mesh under a (4, 4) pose."""
        height, width = shape
        k = np.asarray(intrinsics, dtype=np.float64)
        pose = np.asarray(object_to_camera, dtype=np.float64)
        rotation = pose[:3, :3]
        v = self.vertices @ rotation.T + pose[:3, 3]
        ahead = v[:, 2] > near
        inv_z = 1.0 / np.where(ahead, v[:, 2], np.inf)
        u = k[0, 0] * v[:, 0] * inv_z + k[0, 2]
        w = k[1, 1] * v[:, 1] * inv_z + k[1, 2]

        faces = self.faces
        keep = ahead[faces[:, 0]] & ahead[faces[:, 1]] & ahead[faces[:, 2]]
        if self.cull:  # front faces have the camera centre (object frame) on their outer side
            keep &= self.face_normals @ (-rotation.T @ pose[:3, 3]) > self._face_offsets
        idx = np.flatnonzero(keep)
        setup, idx = _face_setup(u, w, inv_z, faces[idx], idx, width, height)

        depth = np.zeros(height * width, np.float32)
        cosine = np.zeros(height * width, np.float32)
        if len(idx) == 0:
            return depth.reshape(shape), cosine.reshape(shape)
        flat, q, face = _rasterise(setup, width)
        nearest = np.zeros(height * width)
        np.maximum.at(nearest, flat, q)
        won = q >= nearest[flat]
        winner = np.empty(height * width, np.intp)
        winner[flat[won]] = idx[face[won]]
        covered = np.flatnonzero(nearest)
        depth[covered] = 1.0 / nearest[covered]
        rays = pixel_rays(height, width, k[0, 0], k[1, 1], k[0, 2], k[1, 2])[covered] @ rotation
        cosine[covered] = np.abs(np.einsum("ij,ij->i", self.face_normals[winner[covered]], rays))
        return depth.reshape(shape), cosine.reshape(shape)


def _face_setup(u, w, inv_z, faces, idx, width: int, height: int):
    """Edge functions of the faces (k, 3) whose box holds a pixel centre; returns (_Faces, idx)."""
    fu = [u[faces[:, c]] for c in range(3)]
    fw = [w[faces[:, c]] for c in range(3)]
    x0 = np.maximum(np.ceil(np.minimum(np.minimum(fu[0], fu[1]), fu[2])), 0)
    x1 = np.minimum(np.floor(np.maximum(np.maximum(fu[0], fu[1]), fu[2])), width - 1)
    y0 = np.maximum(np.ceil(np.minimum(np.minimum(fw[0], fw[1]), fw[2])), 0)
    y1 = np.minimum(np.floor(np.maximum(np.maximum(fw[0], fw[1]), fw[2])), height - 1)
    e1u, e1w, e2u, e2w = fu[1] - fu[0], fw[1] - fw[0], fu[2] - fu[0], fw[2] - fw[0]
    area = e1u * e2w - e2u * e1w
    sel = np.flatnonzero((x1 >= x0) & (y1 >= y0) & (np.abs(area) > 1e-12))
    area = area[sel]
    a1, b1, a2, b2 = e2w[sel] / area, -e2u[sel] / area, -e1w[sel] / area, e1u[sel] / area
    dx, dy = x0[sel] - fu[0][sel], y0[sel] - fw[0][sel]  # box corner relative to corner 0
    q = [inv_z[faces[sel, c]] for c in range(3)]
    setup = _Faces(
        l1=a1 * dx + b1 * dy, l2=a2 * dx + b2 * dy, a1=a1, b1=b1, a2=a2, b2=b2,
        x0=x0[sel].astype(np.int64), y0=y0[sel].astype(np.int64),
        bw=(x1 - x0)[sel].astype(np.int64) + 1, bh=(y1 - y0)[sel].astype(np.int64) + 1,
        q0=q[0], dq1=q[1] - q[0], dq2=q[2] - q[0],
    )
    return setup, idx[sel]


def _size_class(extent: np.ndarray) -> np.ndarray:
    """Smallest k with 2**k >= extent, as int64 (extent >= 1)."""
    return np.ceil(np.log2(extent)).astype(np.int64)


def _rasterise(faces: _Faces, width: int):
    """(flat pixel index, 1/z, face position) of every pixel centre inside a face."""
    key = _size_class(faces.bh) * 64 + _size_class(faces.bw)
    order = np.argsort(key, kind="stable")
    out = []
    for group in np.split(order, np.flatnonzero(np.diff(key[order])) + 1):
        rows, cols = 1 << int(key[group[0]] // 64), 1 << int(key[group[0]] % 64)
        step = max(1, _BLOCK_CELLS // (rows * cols))
        for start in range(0, len(group), step):
            out.append(_rasterise_block(faces, group[start : start + step], rows, cols, width))
    flat, q, face = (np.concatenate(parts) for parts in zip(*out, strict=True))
    return flat, q, face


def _rasterise_block(faces: _Faces, f, rows: int, cols: int, width: int):
    """Test a (len(f), rows, cols) block of pixel centres against the faces ``f`` at once."""
    i = np.arange(rows, dtype=np.float64)[None, :, None]
    j = np.arange(cols, dtype=np.float64)[None, None, :]
    s = faces._replace(**{name: a[f][:, None, None] for name, a in faces._asdict().items()})
    l1 = s.l1 + s.a1 * j + s.b1 * i
    l2 = s.l2 + s.a2 * j + s.b2 * i
    inside = (l1 >= -_EDGE_EPS) & (l2 >= -_EDGE_EPS) & (l1 + l2 <= 1 + _EDGE_EPS)
    if rows > 1 or cols > 1:
        inside &= (i < s.bh) & (j < s.bw)
    which, r, c = np.nonzero(inside)
    face = f[which]
    q = faces.q0[face] + l1[inside] * faces.dq1[face] + l2[inside] * faces.dq2[face]
    flat = (faces.y0[face] + r) * width + faces.x0[face] + c
    return flat, q, face


class EmbreeRenderer(MeshRenderer):
    """The same images by ray casting with embree (``embreex``), one ray per pixel of the mesh's
    projected box; the first hit wins (``cull`` is moot). ImportError when embreex is missing."""

    engine = "embree"

    def __init__(self, vertices, faces, cull: bool = True):
        super().__init__(vertices, faces, cull)
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector  # needs embreex

        mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        self._intersector = RayMeshIntersector(mesh)

    def render(self, object_to_camera, intrinsics, shape, near: float = 1.0):
        height, width = shape
        k = np.asarray(intrinsics, dtype=np.float64)
        pose = np.asarray(object_to_camera, dtype=np.float64)
        depth = np.zeros(height * width, np.float32)
        cosine = np.zeros(height * width, np.float32)
        v = self.vertices @ pose[:3, :3].T + pose[:3, 3]
        v = v[v[:, 2] > near]
        if len(v) == 0:
            return depth.reshape(shape), cosine.reshape(shape)
        u = k[0, 0] * v[:, 0] / v[:, 2] + k[0, 2]
        w = k[1, 1] * v[:, 1] / v[:, 2] + k[1, 2]
        x0, x1 = max(int(np.ceil(u.min())), 0), min(int(np.floor(u.max())), width - 1)
        y0, y1 = max(int(np.ceil(w.min())), 0), min(int(np.floor(w.max())), height - 1)
        if x1 < x0 or y1 < y0:
            return depth.reshape(shape), cosine.reshape(shape)
        rows, cols = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
        pixels = (rows * width + cols).ravel()
        rays = pixel_rays(height, width, k[0, 0], k[1, 1], k[0, 2], k[1, 2])[pixels]
        rotation = pose[:3, :3]
        origin = -rotation.T @ pose[:3, 3]  # camera centre, object frame
        directions = rays @ rotation  # rotated into the object frame
        origins = np.broadcast_to(origin, directions.shape)
        face, ray, where = self._intersector.intersects_id(
            origins, directions, multiple_hits=False, return_locations=True
        )
        distance = np.einsum("ij,ij->i", where - origin, directions[ray])
        z = distance * rays[ray, 2]
        normal_dot = np.einsum("ij,ij->i", self.face_normals[face], directions[ray])
        hit = z > near  # the first hit on a closed mesh faces the camera: no culling needed
        depth[pixels[ray[hit]]] = z[hit]
        cosine[pixels[ray[hit]]] = np.abs(normal_dot[hit])
        return depth.reshape(shape), cosine.reshape(shape)


def make_renderer(vertices, faces, cull: bool = True, engine: str = "numpy") -> MeshRenderer:
    """A renderer of the mesh with ``engine`` ("numpy" or "embree"; see ``ENGINES``)."""
    if engine not in ENGINES:
        raise ValueError(f"render engine must be one of {ENGINES}, got {engine!r}")
    return (EmbreeRenderer if engine == "embree" else MeshRenderer)(vertices, faces, cull)


def render_depth(vertices, faces, intrinsics, shape, near: float = 1.0, cull: bool = True):
    """Depth and |cosine| (both (H, W) float32) of a mesh whose (n, 3) vertices are already in
    the camera frame; see `MeshRenderer.render`."""
    return MeshRenderer(vertices, faces, cull).render(np.eye(4), intrinsics, shape, near)
