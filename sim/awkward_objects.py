"""Objects that are not star-shaped about the turntable axis, in millimetres (about 150 mm
across): what users put on a scan station beyond vases. Each is one closed, oriented mesh built
with trimesh's boolean backend (manifold3d); ``GENUS`` gives its topology (Euler characteristic
2 − 2g), the ground truth for an atlas reconstruction.

- ``mug``: an open cup with a handle (genus 1; its inside is an overhang).
- ``torus``: a ring lying on the plate (genus 1; no horizontal ray from the axis meets it once).
- ``figurine``: body, head, two thin ears curled almost into tubes, two legs (genus 0).
- ``hook``: a post with an arm whose finger hangs down beside it (an overhang, genus 0).
- ``sheets``: two 1.5 mm plates 3 mm apart (2 % of the diagonal) on a foot (genus 0).

``UNTUNED`` holds objects added after the atlas was tuned on those five, to measure it on shapes
it was not made for: ``chair`` (thin legs and slabs, 8 noise widths thick at σ 0.5 %; genus 0)
and ``knot`` (a trefoil tube, its strands a tube's width apart where they cross; genus 1).
"""

from __future__ import annotations

import numpy as np
import trimesh


def _union(*meshes: trimesh.Trimesh) -> trimesh.Trimesh:
    joined = trimesh.boolean.union(list(meshes), engine="manifold")
    # Faces of at most 8 mm, like a scanned mesh (large flat faces render the same).
    vertices, faces = trimesh.remesh.subdivide_to_size(joined.vertices, joined.faces, 8.0)
    return trimesh.Trimesh(vertices, faces)


def _difference(a: trimesh.Trimesh, b: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.boolean.difference([a, b], engine="manifold")


def _moved(mesh: trimesh.Trimesh, offset, rotation=None) -> trimesh.Trimesh:
    mesh = mesh.copy()
    if rotation is not None:
        mesh.apply_transform(rotation)
    mesh.apply_translation(offset)
    return mesh


def _curled_shell(radius: float, thickness: float, height: float, turn_deg: float,
                  sections: int = 96) -> trimesh.Trimesh:
    """A thin sheet rolled ``turn_deg`` about the z axis (an ear curled almost into a tube)."""
    angle = np.radians(turn_deg)
    ring = trimesh.creation.annulus(radius, radius + thickness, height, sections=sections)
    wedge = trimesh.creation.extrude_polygon(
        _sector_polygon(3 * radius, angle, sections), height * 2)
    wedge.apply_translation((0, 0, -height))
    return trimesh.boolean.intersection([ring, wedge], engine="manifold")


def _sector_polygon(radius: float, angle: float, sections: int):
    from shapely.geometry import Polygon

    phi = np.linspace(0, angle, max(3, int(sections * angle / (2 * np.pi))) + 1)
    return Polygon(np.vstack([[0, 0], np.c_[radius * np.cos(phi), radius * np.sin(phi)]]))


def mug() -> trimesh.Trimesh:
    """A 95 mm mug, 80 mm across, 4 mm wall, with a handle (genus 1, ~20k faces)."""
    outer = _moved(trimesh.creation.cylinder(40, 95, sections=128), (0, 0, 47.5))
    inner = _moved(trimesh.creation.cylinder(36, 95, sections=128), (0, 0, 47.5 + 6))
    handle = trimesh.creation.torus(24, 5, major_sections=96, minor_sections=24)
    upright = trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0))
    handle = _moved(handle, (42, 0, 50), upright)
    cut = _moved(trimesh.creation.cylinder(38, 95, sections=128), (0, 0, 47.5 + 6))
    return _union(_difference(outer, inner), _difference(handle, cut))


def torus() -> trimesh.Trimesh:
    """A ring of 55 mm major and 22 mm minor radius lying on the plate (genus 1)."""
    return _moved(trimesh.creation.torus(55, 22, major_sections=128, minor_sections=48), (0, 0, 22))


def figurine() -> trimesh.Trimesh:
    """A 130 mm figurine: body, head, two thin ears curled 300°, two legs (genus 0)."""
    body = _moved(trimesh.creation.capsule(50, 28, count=(48, 48)), (0, 0, 75))
    head = _moved(trimesh.creation.icosphere(4, 24), (0, 0, 125))
    legs = [_moved(trimesh.creation.cylinder(9, 45, sections=48), (x, 0, 22.5)) for x in (-14, 14)]
    ears = []
    for side in (-1, 1):
        ear = _curled_shell(9, 2, 30, 300)
        tilt = trimesh.transformations.rotation_matrix(side * 0.35, (0, 1, 0))
        ears.append(_moved(ear, (side * 16, 0, 150), tilt))
    figure = _union(body, head, *legs, *ears)
    figure.apply_scale(130.0 / figure.extents[2])  # as tall as the camera frames
    return figure


def hook() -> trimesh.Trimesh:
    """A 125 mm post with an arm whose finger hangs down beside it (an overhang, genus 0)."""
    post = _moved(trimesh.creation.box((24, 24, 125)), (0, 0, 62.5))
    arm = _moved(trimesh.creation.box((70, 20, 18)), (30, 0, 116))
    finger = _moved(trimesh.creation.box((16, 20, 70)), (57, 0, 90))
    foot = _moved(trimesh.creation.box((60, 60, 8)), (0, 0, 4))
    return _union(post, arm, finger, foot)


def sheets() -> trimesh.Trimesh:
    """Two 100 × 100 × 1.5 mm plates 3 mm apart standing on a 10 mm foot (genus 0)."""
    foot = _moved(trimesh.creation.box((12, 100, 10)), (0, 0, 5))
    plates = [_moved(trimesh.creation.box((1.5, 100, 100)), (x, 0, 58)) for x in (-2.25, 2.25)]
    return _union(foot, *plates)


def chair() -> trimesh.Trimesh:
    """A 130 mm chair: an 80 × 80 × 8 mm seat on four 7 mm square legs, a 7 mm thick back
    (genus 0)."""
    seat = _moved(trimesh.creation.box((80, 80, 8)), (0, 0, 64))
    legs = [_moved(trimesh.creation.box((7, 7, 60)), (x, y, 30))
            for x in (-36.5, 36.5) for y in (-36.5, 36.5)]
    back = _moved(trimesh.creation.box((80, 7, 62)), (0, 36.5, 99))
    return _union(seat, *legs, back)


def knot() -> trimesh.Trimesh:
    """A trefoil knot of a 12 mm tube, about 120 mm across (genus 1: a knotted torus)."""
    from shapely.geometry import Point

    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    path = 20.0 * np.c_[np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t),
                        -np.sin(3 * t)]
    tube = trimesh.creation.sweep_polygon(Point(0, 0).buffer(6.0, quad_segs=16),
                                          np.vstack([path, path[:1]]), connect=True)
    return _moved(tube, (0, 0, -tube.bounds[0, 2]))


def tray() -> trimesh.Trimesh:
    """A 100 × 100 × 15 mm tray with 2 mm walls and floor (genus 0): walls a few noise widths
    thick (σ 0.5 % of its diagonal is 0.72 mm)."""
    outer = _moved(trimesh.creation.box((100, 100, 15)), (0, 0, 7.5))
    hollow = _moved(trimesh.creation.box((96, 96, 15)), (0, 0, 7.5 + 2))
    return _difference(outer, hollow)


AWKWARD = {"mug": mug, "torus": torus, "figurine": figurine, "hook": hook, "sheets": sheets}
UNTUNED = {"chair": chair, "knot": knot, "tray": tray}
GENUS = {"mug": 1, "torus": 1, "figurine": 0, "hook": 0, "sheets": 0, "chair": 0, "knot": 1,
         "tray": 0}


def sample_cloud(mesh: trimesh.Trimesh, n_points: int, noise: float, random_state=0):
    """A noisy cloud of ``mesh``: (n_points, 3) area-uniform samples moved by Gaussian noise of
    ``noise`` × the bounding-box diagonal along each axis."""
    rng = np.random.default_rng(random_state)
    points, _ = trimesh.sample.sample_surface(mesh, n_points, seed=rng.integers(2**31))
    diagonal = float(np.linalg.norm(mesh.extents))
    return points + rng.normal(0.0, noise * diagonal, points.shape)


def relief(size: float = 140.0, cells: int = 280, holes: int = 3, seed: int = 3) -> trimesh.Trimesh:
    """An open range scan: a height field with detail at several scales (wavelengths from 70
    to 7 mm) and ``holes`` round holes 12–20 mm wide, as a face or relief scan has (not closed)."""
    rng = np.random.default_rng(seed)
    u = np.linspace(-size / 2, size / 2, cells + 1)
    x, y = np.meshgrid(u, u, indexing="ij")
    z = np.zeros_like(x)
    for wavelength, amplitude in ((70, 9.0), (30, 3.0), (14, 1.2), (7, 0.5)):
        for _ in range(3):
            k = 2 * np.pi / wavelength * rng.normal(size=2) / np.sqrt(2)
            z += amplitude / 3 * np.sin(k[0] * x + k[1] * y + rng.uniform(0, 2 * np.pi))
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a = (i * (cells + 1) + j).ravel()
    faces = np.concatenate([np.column_stack([a, a + cells + 1, a + 1]),
                            np.column_stack([a + 1, a + cells + 1, a + cells + 2])])
    centres = vertices[faces].mean(axis=1)[:, :2]
    keep = np.ones(len(faces), bool)
    for _ in range(holes):
        centre = rng.uniform(-size / 3, size / 3, 2)
        keep &= np.linalg.norm(centres - centre, axis=1) > rng.uniform(6, 10)
    mesh = trimesh.Trimesh(vertices, faces[keep])
    mesh.remove_unreferenced_vertices()
    return mesh
