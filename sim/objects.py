"""Objects for the simulated camera: built-in procedural meshes and any mesh file, in millimetres,
stood on the plate (lowest point at z = 0) and centred on the turntable axis."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh

from drivers.errors import DeviceError

from .awkward_objects import AWKWARD, UNTUNED

log = logging.getLogger(__name__)


class ObjectError(DeviceError, ValueError):
    """The simulated camera's object cannot be loaded (the message names the cause)."""


def _revolve(radius: np.ndarray, heights: np.ndarray) -> trimesh.Trimesh:
    """A closed, outward-wound surface about the z axis.

    radius : (k, s) mm at each of k heights (k,) mm and s angles 2π·j/s; capped at both ends.
    """
    k, s = radius.shape
    phi = 2 * np.pi * np.arange(s) / s
    rings = np.stack([radius * np.cos(phi), radius * np.sin(phi),
                      np.broadcast_to(heights[:, None], radius.shape)], axis=-1)
    vertices = np.concatenate([rings.reshape(-1, 3), [[0, 0, heights[0]], [0, 0, heights[-1]]]])
    a = (np.arange(k - 1)[:, None] * s + np.arange(s)[None, :]).ravel()
    b = (np.arange(k - 1)[:, None] * s + (np.arange(s)[None, :] + 1) % s).ravel()
    side = np.concatenate([np.column_stack([a, b, b + s]), np.column_stack([a, b + s, a + s])])
    j = np.arange(s)
    bottom = np.column_stack([np.full(s, k * s), (j + 1) % s, j])
    top = np.column_stack([np.full(s, k * s + 1), (k - 1) * s + j, (k - 1) * s + (j + 1) % s])
    return trimesh.Trimesh(vertices, np.concatenate([side, bottom, top]), process=False)


def vase(sections: int = 240, rows: int = 110) -> trimesh.Trimesh:
    """A 120 mm vase: bulging fluted body, narrow neck, flared lip (~53k faces)."""
    t = np.linspace(0, 1, rows)[:, None]
    phi = 2 * np.pi * np.arange(sections)[None, :] / sections
    lip = 8 * np.exp(-(((t - 0.95) / 0.06) ** 2))
    profile = 28 + 14 * np.sin(np.pi * t * 1.3) ** 2 - 10 * t + lip
    body = np.sin(np.pi * np.clip(t / 0.7, 0, 1))  # flutes fade out towards the foot and neck
    radius = profile * (1 + 0.05 * body * np.cos(7 * phi) + 0.03 * t * np.cos(phi))
    return _revolve(radius, 120 * t[:, 0])


def bust(subdivisions: int = 5) -> trimesh.Trimesh:
    """A bunny-like blob, ~95 mm tall: a displaced sphere with an "ear" and a "nose" and a flat
    base (~20k faces)."""
    sphere = trimesh.creation.icosphere(subdivisions, 1.0)
    v = sphere.vertices
    bumps = (0.25 * np.exp(-((v[:, 0] - 0.5) ** 2 + (v[:, 2] - 0.8) ** 2) / 0.05)  # an "ear"
             + 0.15 * np.exp(-((v[:, 1] - 0.8) ** 2 + (v[:, 2] - 0.2) ** 2) / 0.08)  # a "nose"
             + 0.04 * np.sin(5 * v[:, 0]) * np.cos(4 * v[:, 1]))
    vertices = v * (1 + bumps)[:, None] * np.array([45.0, 40.0, 50.0])
    vertices[:, 2] = np.maximum(vertices[:, 2], -35.0)  # flat base to stand on
    return trimesh.Trimesh(vertices, sphere.faces, process=False)


def box(subdivisions: int = 6) -> trimesh.Trimesh:
    """An 80 × 60 × 100 mm box, its faces subdivided (~49k triangles) like a scanned mesh."""
    mesh = trimesh.creation.box((80.0, 60.0, 100.0))
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    return mesh


BUILT_IN = {"vase": vase, "bust": bust, "box": box, **AWKWARD, **UNTUNED}
DEFAULT_OBJECT = "vase"


def stand_on_plate(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy of ``mesh`` moved so its lowest point is at z = 0 and its x/y box is centred on
    the axis; a closed mesh wound inside-out is turned outward (the renderer culls back faces)."""
    low, high = mesh.bounds
    shift = -np.array([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]])
    placed = trimesh.Trimesh(mesh.vertices + shift, mesh.faces, process=False)
    if placed.is_watertight and placed.is_winding_consistent and placed.volume < 0:
        placed.invert()
    return placed


def load_object(name_or_path: str | Path | None = None) -> trimesh.Trimesh:
    """A built-in object by name (``vase``, ``bust``, ``box``, one of `AWKWARD`: ``mug``,
    ``torus``, ``figurine``, ``hook``, ``sheets``, or of `UNTUNED`: ``chair``, ``knot``,
    ``tray``) or
    any mesh file trimesh reads
    (units: mm), stood on the plate. Raises `ObjectError` with a one-line cause."""
    if name_or_path is not None and not str(name_or_path).strip():
        raise ObjectError(f"object {str(name_or_path)!r}: an empty name (built-in objects: "
                          f"{', '.join(BUILT_IN)}; or a mesh file)")
    name = str(name_or_path or DEFAULT_OBJECT)
    if name in BUILT_IN:
        return stand_on_plate(BUILT_IN[name]())
    path = Path(name)
    if not path.exists():
        known = ", ".join(BUILT_IN)
        raise ObjectError(f"object {name!r}: no such file (built-in objects: {known})")
    if not path.is_file():
        raise ObjectError(f"object {path}: not a file")
    try:
        loaded = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many kinds for unreadable files
        cause = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ObjectError(f"object {path}: unreadable mesh ({cause})") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ObjectError(f"object {path}: holds no triangles (not a mesh, or empty)")
    if not np.isfinite(loaded.vertices).all():
        raise ObjectError(f"object {path}: has NaN or infinite vertices")
    size = float(np.ptp(loaded.vertices, axis=0).max())
    if size < 5.0:
        log.warning("object %s is only %.3g mm across: is it in metres? (expected mm)", path, size)
    return stand_on_plate(loaded)
