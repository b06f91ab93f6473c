"""Closed objects: a 360° scan as disc-like patches, merged into one mesh without doubled layers.

The paper's method maps one 2D parameter domain to the surface, so it can hold a disc, not the
closed surface a full turn of the table sees. The merged cloud (object frame, z up the axis) is
split into patches that are discs:

* ``n_sectors`` angular sectors about the axis (default 6 × 60°), each widened by ``overlap_deg``
  on both sides, and cut off at the cap height when there is a cap;
* a top cap (the points above ``cap_height``, widened downwards by ``cap_overlap_mm``) when the
  top is closed, i.e. the scan has points near the axis at the top.

`PatchSplit.split` cuts the cloud into patches (`Patch`: points mask, trim planes) and `merge`
joins their meshes; `PatchReconstructor` composes them with one reconstruction per patch, and
the scan engine (`capture.live`) composes them with fits it keeps between updates.

Each patch is reconstructed on its own (``reconstructor``: the paper's `SurfaceReconstructor` by
default), oriented outwards (`trim`), then trimmed back to its core with the SAME planes as its
neighbours:
the half-planes through the axis at the sector boundary angles and the horizontal plane at the cap
height (`trimesh.Trimesh.slice_plane`). Neighbouring patches therefore end on the same plane and
never overlap; the two seam polylines in each plane are zipped with a strip of triangles (a wall
as high as the two reconstructions disagree there, oriented outwards) and vertices that coincide
are merged. The overlaps only give each patch context at its cut, where the spline boundary of a
lone patch would be rounded.

Supported topology: genus-0 surfaces that are star-shaped about the turntable axis at every
height (each horizontal half-line from the axis crosses the surface once), open at the bottom
(the plate) and with a closed or open top: surfaces of revolution, vases, busts, bottles. Not
supported: handles and through-holes (genus > 0), overhangs or folds that a half-line from the
axis crosses more than once (a cup's inside, an ear folding back), and parts not connected to the
region near the axis. `unfaithful_patch` says when a split's fits show such a surface (a patch
the paper's method could not mesh as one disc): an atlas of charts (`reconstruct.atlas`) then
meshes the whole cloud instead.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import trimesh
from sklearn.base import BaseEstimator, clone

from reconstruct.errors import InvalidInputError

from .faithfulness import FOLD_LIMIT, UNEXPLAINED_LIMIT, fold_share, unexplained_fraction
from .mesh_edges import turn_faces

log = logging.getLogger(__name__)


def _default_reconstructor(random_state):
    from reconstruct.pipeline import SurfaceReconstructor

    return SurfaceReconstructor(random_state=random_state, atlas="never", up=None)  # a chart


def _outward(points: np.ndarray, reference_z: float | None) -> np.ndarray:
    """(n, 3) outward directions: radial from the axis, or from (0, 0, reference_z) for a cap."""
    out = points.copy()
    out[:, 2] = 0.0 if reference_z is None else points[:, 2] - reference_z
    return out


def _orient_outwards(mesh: trimesh.Trimesh, reference_z: float | None) -> trimesh.Trimesh:
    flux = (
        np.einsum("ij,ij->i", mesh.face_normals, _outward(mesh.triangles_center, reference_z))
        @ mesh.area_faces
    )
    if flux < 0:
        turn_faces(mesh)  # not trimesh's invert: it keeps the face normals just read
    return mesh


def _seam_vertices(mesh: trimesh.Trimesh, normal, offset: float, keep=None) -> np.ndarray:
    """Indices of the boundary vertices of ``mesh`` lying on the plane x·normal = offset."""
    if len(mesh.faces) == 0:
        return np.empty(0, dtype=int)
    edges = mesh.edges_sorted
    boundary = edges[trimesh.grouping.group_rows(edges, require_count=1)]
    candidates = np.unique(boundary)
    verts = mesh.vertices[candidates]
    eps = 1e-6 * max(1.0, float(np.abs(mesh.vertices).max()))
    on = np.abs(verts @ normal - offset) < eps
    if keep is not None:
        on &= keep(verts)
    return candidates[on]


def zip_seam(va, vb, param_a, param_b, plane_normal, closed=False, max_edge=np.inf):
    """Triangles (k, 3) joining two polylines that follow the same seam curve.

    va, vb : (m, 3), (n, 3) seam vertices of the two sides (indices 0..m-1 and m..m+n-1 in the
    result); param_a, param_b : their position along the seam (z, or the angle for a loop);
    plane_normal : (3,) normal of the seam plane pointing from side a to side b. Each triangle
    is oriented outwards (away from the axis side that has material on both sides).
    """
    if len(va) < 2 or len(vb) < 2:
        return np.empty((0, 3), dtype=int)
    ia, ib = np.argsort(param_a), np.argsort(param_b)
    pa, pb = np.asarray(param_a)[ia], np.asarray(param_b)[ib]
    ia, ib = ia, ib + len(va)
    if closed:  # repeat each loop's first vertex one turn later
        ia, pa = np.r_[ia, ia[0]], np.r_[pa, pa[0] + 2 * np.pi]
        ib, pb = np.r_[ib, ib[0]], np.r_[pb, pb[0] + 2 * np.pi]
    side = np.r_[np.zeros(len(pa), bool), np.ones(len(pb), bool)]
    order = np.argsort(np.r_[pa, pb], kind="stable")
    side = side[order]
    count_a = np.cumsum(~side) - 1  # index into the sorted a list after each event
    count_b = np.cumsum(side) - 1
    step = np.ones(len(side), dtype=bool)
    step[np.flatnonzero(~side)[0]] = step[np.flatnonzero(side)[0]] = False  # the two starts
    ja, jb = np.maximum(count_a, 0), np.maximum(count_b, 0)
    tri_a = np.c_[ia[np.maximum(count_a - 1, 0)], ia[ja], ib[jb]][step & ~side]
    tri_b = np.c_[ia[ja], ib[np.maximum(count_b - 1, 0)], ib[jb]][step & side]
    faces = np.concatenate([tri_a, tri_b])
    vertices = np.concatenate([va, vb])
    corners = vertices[faces]
    lengths = np.linalg.norm(corners - corners[:, [1, 2, 0]], axis=2)
    faces = faces[lengths.max(axis=1) <= max_edge]
    # Outwards: the wall faces the side whose surface lies nearer the axis.
    corners = vertices[faces]
    radius = np.hypot(corners[..., 0], corners[..., 1])
    from_a = faces < len(va)
    ra = np.where(from_a, radius, 0).sum(1) / np.maximum(from_a.sum(1), 1)
    rb = np.where(~from_a, radius, 0).sum(1) / np.maximum((~from_a).sum(1), 1)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    flip = (normals @ np.asarray(plane_normal)) * np.sign(ra - rb) < 0
    faces[flip] = faces[flip][:, ::-1]
    return faces


@dataclasses.dataclass(frozen=True)
class Patch:
    """One disc-like piece of a closed cloud.

    name : "sector k (a° to b°)" or "cap".  mask : (n,) bool, its points among the split ones.
    planes : ((origin (3,), normal (3,)), ...) the trim planes; the kept side is the normal's.
    reference_z : None for a sector (outwards is radial), else the height the cap faces away
    from."""

    name: str
    mask: np.ndarray
    planes: tuple
    reference_z: float | None

    @property
    def is_cap(self) -> bool:
        return self.reference_z is not None


@dataclasses.dataclass(frozen=True)
class PatchLayout:
    """The patches of one split. boundaries_deg : (n_sectors,) seam angles; cap_height : mm,
    None without a cap."""

    patches: tuple[Patch, ...]
    boundaries_deg: np.ndarray
    cap_height: float | None

    @property
    def has_cap(self) -> bool:
        return self.cap_height is not None


class PatchSplit(BaseEstimator):
    """Split a closed (360°) object-frame cloud into sectors and a cap; merge their meshes.

    n_sectors : angular sectors about the axis; overlap_deg : widening of each on both sides.
    start_deg : angle of the first sector boundary.
    cap : "auto" (a cap when the top is closed), True or False.
    cap_fraction : the cap is the top ``cap_fraction`` of the object's height.
    cap_overlap_mm : widening of the cap downwards and of the sectors upwards (None: 10% of height).
    min_points : fewest points a patch may have (the closed-top test counts up to it).
    """

    def __init__(self, n_sectors: int = 6, overlap_deg: float = 20.0, start_deg: float = 0.0,
                 cap="auto", cap_fraction: float = 0.2, cap_overlap_mm: float | None = None,
                 min_points: int = 50):
        self.n_sectors = n_sectors
        self.overlap_deg = overlap_deg
        self.start_deg = start_deg
        self.cap = cap
        self.cap_fraction = cap_fraction
        self.cap_overlap_mm = cap_overlap_mm
        self.min_points = min_points

    def check(self, points) -> np.ndarray:
        """(n, 3) float64 finite points; `InvalidInputError` for them or a bad parameter."""
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
            raise InvalidInputError(f"expected finite points of shape (n, 3), got {points.shape}")
        if len(points) == 0:
            raise InvalidInputError("no points to split")
        if self.n_sectors < 3:
            raise InvalidInputError(f"n_sectors must be >= 3, got {self.n_sectors}")
        width = 360.0 / self.n_sectors
        if not 0 <= self.overlap_deg < min(width, 180 - width / 2):
            raise InvalidInputError(
                f"overlap_deg must be in [0, {width:g}), got {self.overlap_deg}"
            )
        if not 0 < self.cap_fraction < 1:
            raise InvalidInputError(f"cap_fraction must be in (0, 1), got {self.cap_fraction}")
        return points

    def _top_is_closed(self, points, cap_height) -> bool:
        """A closed top has points near the axis above the cap height."""
        radius = np.hypot(points[:, 0], points[:, 1])
        top = points[:, 2] >= cap_height
        band = (points[:, 2] < cap_height) & (
            points[:, 2] >= cap_height - 0.05 * np.ptp(points[:, 2])
        )
        reference = np.median(radius[band]) if band.any() else np.median(radius[top])
        return int((top & (radius < 0.3 * reference)).sum()) >= min(20, self.min_points)

    def split(self, points) -> PatchLayout:
        """The patches of (n, 3) object-frame points (z up the axis, mm): sectors, then cap."""
        points = self.check(points)
        z = points[:, 2]
        height = float(np.ptp(z))
        cap_overlap = 0.1 * height if self.cap_overlap_mm is None else float(self.cap_overlap_mm)
        cap_height = float(z.max() - self.cap_fraction * height)
        has_cap = self._top_is_closed(points, cap_height) if self.cap == "auto" else bool(self.cap)
        width = 360.0 / self.n_sectors
        bounds = self.start_deg + width * np.arange(self.n_sectors)
        phi = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
        patches = []
        for k, start in enumerate(bounds):
            delta = (phi - (start + width / 2) + 180.0) % 360.0 - 180.0
            mask = np.abs(delta) <= width / 2 + self.overlap_deg
            planes = []
            for angle, sign in ((start, 1), (start + width, -1)):
                a = np.radians(angle)
                planes.append((np.zeros(3), sign * np.array([-np.sin(a), np.cos(a), 0.0])))
            if has_cap:
                mask &= z <= cap_height + cap_overlap
                planes.append((np.array([0, 0, cap_height]), np.array([0, 0, -1.0])))
            name = f"sector {k} ({start:g}° to {start + width:g}°)"
            patches.append(Patch(name, mask, tuple(planes), None))
        if has_cap:
            mask = z >= cap_height - cap_overlap
            planes = ((np.array([0, 0, cap_height]), np.array([0, 0, 1.0])),)
            patches.append(Patch("cap", mask, planes, cap_height - height / 2))
        return PatchLayout(tuple(patches), bounds, cap_height if has_cap else None)


def trim(mesh: trimesh.Trimesh, patch: Patch) -> trimesh.Trimesh:
    """A copy of a patch's ``mesh`` oriented outwards and cut back to its trim planes."""
    mesh = _orient_outwards(
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False), patch.reference_z
    )
    for origin, normal in patch.planes:
        mesh = mesh.slice_plane(origin, normal)
    return mesh


def unfaithful_patch(models, limit: float | None = None) -> str | None:
    """One line naming the first unfaithful fit among ``models`` ({patch name: fitted
    `SurfaceReconstructor`}), else None. Unfaithful: its mesh leaves over ``limit`` (None:
    ``UNEXPLAINED_LIMIT``) of its points unexplained, or folds over
    (`faithfulness.fold_share` over ``FOLD_LIMIT``): the patch is not one disc-like
    surface (a cup's inside and outside, a handle, an overhang, a curled ear), so the sectors
    do not mesh the object faithfully.

    Measured on 36-view simulated scans (the worst sector): vase and torus 0.000, figurine
    0.032, mug 0.125, two close sheets 0.337, hook 0.447 of the points unexplained."""
    limit = UNEXPLAINED_LIMIT if limit is None else float(limit)

    for name in sorted(models):
        model = models[name]
        unexplained = getattr(model, "unexplained_", None)
        if unexplained is None:
            unexplained = unexplained_fraction(model.mesh_, model.points_)
        if unexplained > limit:
            return (f"{name} leaves {100 * unexplained:.0f} % of its points unexplained: "
                    "not one disc-like surface")
        folds = fold_share(model.mesh_)
        if folds > FOLD_LIMIT:
            return f"{name}'s mesh folds over ({100 * folds:.1f} % of its edges)"
    return None


def empty_mesh() -> trimesh.Trimesh:
    return trimesh.Trimesh(np.empty((0, 3)), np.empty((0, 3), dtype=int), process=False)


class PatchReconstructor(BaseEstimator):
    """Reconstruct a closed (360°) object-frame cloud as trimmed disc patches merged into one mesh:
    `PatchSplit.split`, one reconstruction per patch, `trim`, `merge`.

    n_sectors, overlap_deg, start_deg, cap, cap_fraction, cap_overlap_mm, min_points : the
        split (`PatchSplit`); a patch with fewer than ``min_points`` points is an error.
    reconstructor : estimator with ``fit(points (n, 3))`` and ``mesh_`` (cloned per patch), or a
        callable ``f(random_state)`` returning one; None: the paper's `SurfaceReconstructor`.
    random_state : seed handed to each patch's reconstructor.

    Fitted: ``mesh_`` (trimesh.Trimesh), ``patch_meshes_`` (trimmed, one per patch),
    ``patch_names_``, ``patch_sizes_`` (points per patch), ``has_cap_``, ``cap_height_`` (mm or
    None), ``boundaries_deg_`` (n_sectors,) seam angles, ``n_seam_faces_``.
    """

    def __init__(
        self,
        n_sectors: int = 6,
        overlap_deg: float = 20.0,
        start_deg: float = 0.0,
        cap="auto",
        cap_fraction: float = 0.2,
        cap_overlap_mm: float | None = None,
        reconstructor=None,
        min_points: int = 50,
        random_state=0,
    ):
        self.n_sectors = n_sectors
        self.overlap_deg = overlap_deg
        self.start_deg = start_deg
        self.cap = cap
        self.cap_fraction = cap_fraction
        self.cap_overlap_mm = cap_overlap_mm
        self.reconstructor = reconstructor
        self.min_points = min_points
        self.random_state = random_state

    def _new_reconstructor(self):
        if self.reconstructor is None:
            return _default_reconstructor(self.random_state)
        if hasattr(self.reconstructor, "fit"):
            return clone(self.reconstructor)
        return self.reconstructor(self.random_state)

    def fit(self, points, y=None):
        """Reconstruct (n, 3) object-frame points (z up the axis, mm); returns self."""
        split = PatchSplit(n_sectors=self.n_sectors, overlap_deg=self.overlap_deg,
                           start_deg=self.start_deg, cap=self.cap, cap_fraction=self.cap_fraction,
                           cap_overlap_mm=self.cap_overlap_mm, min_points=self.min_points)
        points = split.check(points)
        layout = split.split(points)
        meshes = []
        for patch in layout.patches:
            n = int(patch.mask.sum())
            if n < self.min_points:
                raise InvalidInputError(f"patch {patch.name} has {n} points, need >= "
                                        f"{self.min_points}: the scan misses that side")
            log.info("patch %s: reconstructing %d points", patch.name, n)
            meshes.append(trim(self._new_reconstructor().fit(points[patch.mask]).mesh_, patch))
        self.patch_meshes_ = meshes
        self.patch_names_ = [p.name for p in layout.patches]
        self.patch_sizes_ = [int(p.mask.sum()) for p in layout.patches]
        self.has_cap_ = layout.has_cap
        self.cap_height_ = layout.cap_height
        self.boundaries_deg_ = layout.boundaries_deg
        self.mesh_, self.n_seam_faces_ = merge(meshes, layout)
        return self


def merge(meshes, layout: PatchLayout) -> tuple[trimesh.Trimesh, int]:
    """(mesh, seam faces): the trimmed patch meshes (one per ``layout`` patch, in order; empty
    for a patch left open) concatenated, every seam zipped, coinciding vertices merged."""
    if not any(len(m.faces) for m in meshes):
        return empty_mesh(), 0
    bounds, cap_height = layout.boundaries_deg, layout.cap_height
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    vertices = np.concatenate([m.vertices for m in meshes])
    faces = [m.faces + o for m, o in zip(meshes, offsets, strict=False)]
    edges = np.concatenate([m.edges_unique_length for m in meshes if len(m.faces)])
    max_edge = 4.0 * float(np.median(edges))
    seams = []
    n = len(bounds)
    for k in range(n):  # the seam at bounds[k] joins sector k - 1 (side a) and sector k
        a = np.radians(bounds[k])
        radial, normal = (
            np.array([np.cos(a), np.sin(a), 0.0]),
            np.array([-np.sin(a), np.cos(a), 0]),
        )

        def keep(v, radial=radial):
            inside = v @ radial > 0
            return inside if cap_height is None else inside & (v[:, 2] <= cap_height + 1e-9)

        ia = _seam_vertices(meshes[(k - 1) % n], normal, 0.0, keep) + offsets[(k - 1) % n]
        ib = _seam_vertices(meshes[k], normal, 0.0, keep) + offsets[k]
        seams.append((ia, ib, vertices[ia, 2], vertices[ib, 2], normal, False))
    if cap_height is not None:
        up = np.array([0, 0, 1.0])
        ia = np.concatenate(
            [
                _seam_vertices(m, up, cap_height) + o
                for m, o in zip(meshes[:n], offsets[:n], strict=True)
            ]
        )
        ib = _seam_vertices(meshes[n], up, cap_height) + offsets[n]
        angle = [np.arctan2(vertices[i, 1], vertices[i, 0]) for i in (ia, ib)]
        seams.append((ia, ib, angle[0], angle[1], up, True))
    n_seam = 0
    for ia, ib, pa, pb, normal, closed in seams:
        local = zip_seam(vertices[ia], vertices[ib], pa, pb, normal, closed, max_edge)
        faces.append(np.r_[ia, ib][local])
        n_seam += len(local)
    mesh = trimesh.Trimesh(vertices, np.concatenate(faces), process=False)
    mesh.merge_vertices()
    f = mesh.faces
    mesh.update_faces((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0]))
    mesh.remove_unreferenced_vertices()
    log.info("merged %d patches: %d faces (%d on seams)", len(meshes), len(mesh.faces), n_seam)
    return mesh, n_seam
