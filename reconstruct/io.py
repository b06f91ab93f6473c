"""Reading point clouds (PLY, XYZ/CSV text, NPY), writing meshes (PLY, OBJ, STL, GLB) and clouds
(PLY), and the fitted-state archive (`write_state` / `read_state`: a JSON header and named
arrays in one .npz).

A PLY is written in single precision (float32, as trimesh writes it) when that holds the
vertices, else in double: a cloud in map coordinates (a 150 mm object 5,000 km from the origin)
rounds to half a metre in float32, and a mesh of it written so has no face left with an area.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
import warnings
import zipfile
from pathlib import Path

import numpy as np
import trimesh

from .errors import InvalidInputError, ReconstructionWarning

POINT_FORMATS = (".ply", ".xyz", ".txt", ".csv", ".pts", ".pcd", ".npy")
MESH_FORMATS = (".ply", ".obj", ".stl", ".glb")
#: Mesh formats whose vertices are single precision whatever the mesh needs.
SINGLE_PRECISION_FORMATS = ("stl", "glb")
#: Single precision holds vertices when rounding them to it moves none by more than this share
#: of their box's diagonal (a 150 mm object: 0.15 µm) and collapses no edge of a face.
SINGLE_PRECISION_TOLERANCE = 1e-6


def read_points(path: str | os.PathLike) -> np.ndarray:
    """Read a point cloud file into (n, 3) float64 (x, y, z: the first three columns/properties).

    Raises `InvalidInputError` with a one-line message naming the file and the cause.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in POINT_FORMATS:
        raise InvalidInputError(
            f"{path}: unsupported point cloud format {suffix or '(none)'!r} "
            f"(use one of {', '.join(POINT_FORMATS)})"
        )
    if not path.is_file():
        what = "is a directory, not a point cloud file" if path.is_dir() else "no such file"
        raise InvalidInputError(f"{path}: {what}")
    if path.stat().st_size == 0:
        raise InvalidInputError(f"{path}: file is empty")
    try:
        if suffix == ".npy":
            points = np.load(path, allow_pickle=False)
        elif suffix == ".ply":
            points = _read_ply(path)
        elif suffix == ".pcd":
            points = _read_pcd(path)
        else:
            points = _read_text(path)
    except InvalidInputError:
        raise
    except Exception as exc:  # every parser failure becomes one line naming the file
        raise InvalidInputError(f"{path}: cannot read {suffix[1:].upper()} ({exc})") from exc
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InvalidInputError(f"{path}: expected rows of x, y, z, got shape {points.shape}")
    if len(points) == 0:
        raise InvalidInputError(f"{path}: holds no points")
    if points.dtype.kind not in "iuf":  # an .npy of strings, objects, complex numbers
        raise InvalidInputError(f"{path}: its values are {points.dtype}, not real numbers")
    return np.ascontiguousarray(points[:, :3], dtype=np.float64)


def _read_ply(path: Path) -> np.ndarray:
    with open(path, "rb") as handle:
        if handle.read(3) != b"ply":
            raise InvalidInputError(f"{path}: malformed PLY (missing 'ply' magic)")
    loaded = trimesh.load(path, force=None, process=False)
    if isinstance(loaded, trimesh.Scene):
        geometries = list(loaded.geometry.values())
        if not geometries:
            raise InvalidInputError(f"{path}: PLY holds no vertices")
        vertices = np.vstack([np.asarray(g.vertices) for g in geometries])
    else:
        vertices = np.asarray(loaded.vertices)
    if len(vertices) == 0:
        raise InvalidInputError(f"{path}: PLY holds no vertices")
    declared = _ply_vertex_count(path)
    if declared is not None and declared != len(vertices):  # trimesh's ASCII reader takes
        raise InvalidInputError(f"{path}: its header says {declared} vertices, it holds "  # the
                                f"{len(vertices)} (a truncated or damaged PLY file)")  # rows
    return vertices


def _ply_vertex_count(path: Path) -> int | None:
    """The vertex count a PLY header declares (``element vertex N``), or None if it names
    none in its first 64 kB."""
    with open(path, "rb") as handle:
        header = handle.read(1 << 16).split(b"end_header", 1)[0]
    for line in header.decode("ascii", errors="replace").splitlines():
        words = line.split()
        if words[:2] == ["element", "vertex"] and len(words) == 3:
            try:
                return int(words[2])
            except ValueError:
                raise InvalidInputError(f"{path}: malformed PLY (element vertex "
                                        f"{words[2][:20]!r})") from None
    return None


#: A PCD header's TYPE letters as numpy's kinds.
_PCD_KINDS = {"F": "f", "I": "i", "U": "u"}


def _read_pcd(path: Path) -> np.ndarray:
    """The x, y, z fields of a Point Cloud Library file (PCD v0.7, ``DATA ascii`` or
    ``binary``; not ``binary_compressed``, whose LZF needs a library we do not ship)."""
    header = {}
    with open(path, "rb") as handle:
        while "DATA" not in header:
            line = handle.readline()
            if not line:
                raise InvalidInputError(f"{path}: malformed PCD (no DATA line in its header)")
            words = line.decode("ascii", errors="replace").split()
            if words and not words[0].startswith("#"):
                header[words[0].upper()] = words[1:]
        body = handle.read()
    fields = header.get("FIELDS", [])
    counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
    if not {"x", "y", "z"} <= set(fields):
        raise InvalidInputError(f"{path}: its PCD fields are {' '.join(fields) or 'none'}, "
                                f"without x, y and z")
    if len(counts) != len(fields) or len(header.get("SIZE", [])) != len(fields) or len(
            header.get("TYPE", [])) != len(fields):
        raise InvalidInputError(f"{path}: malformed PCD (FIELDS, SIZE, TYPE and COUNT differ "
                                f"in length)")
    n = int(header.get("POINTS", [0])[0]) or int(np.prod(
        [int(header.get(k, ["1"])[0]) for k in ("WIDTH", "HEIGHT")]))
    kind = (header["DATA"] or ["?"])[0].lower()
    if kind == "ascii":
        first = np.cumsum([0, *counts])  # a field of COUNT k takes k columns
        rows = [line for line in body.decode("ascii", errors="replace").splitlines()
                if line.strip()]
        if not rows:
            return np.zeros((0, 3))  # (said to hold no points)
        if len(rows) != n:
            raise InvalidInputError(f"{path}: its header says {n} points, it holds {len(rows)} "
                                    f"rows (a truncated or damaged PCD file)")
        return _loaded_rows(path, rows, None, [int(first[fields.index(a)]) for a in "xyz"])
    if kind != "binary":
        raise InvalidInputError(f"{path}: PCD data {kind!r} is not read: save it as binary or "
                                f"ascii (PCL's pcl_convert_pcd_ascii_binary)")
    try:
        dtype = np.dtype([(f"f{i}", "<" + _PCD_KINDS[t.upper()] + s, (c,) if c > 1 else ())
                          for i, (t, s, c) in enumerate(zip(header["TYPE"], header["SIZE"],
                                                            counts, strict=True))])
    except (KeyError, TypeError) as exc:
        raise InvalidInputError(f"{path}: malformed PCD (TYPE {' '.join(header['TYPE'])}, "
                                f"SIZE {' '.join(header['SIZE'])})") from exc
    if len(body) < n * dtype.itemsize:
        raise InvalidInputError(f"{path}: its header says {n} points, it holds "
                                f"{len(body) // dtype.itemsize} (a truncated PCD file)")
    data = np.frombuffer(body, dtype, count=n)
    return np.column_stack([data[f"f{fields.index(a)}"] for a in "xyz"]).astype(np.float64)


def _read_text(path: Path) -> np.ndarray:
    """Rows of x, y, z and any further columns (normals, colour, intensity), split by spaces,
    tabs, commas or semicolons (then a decimal comma is read as a point), after an optional
    header line of words; a PTS file's lines giving its blocks' point counts (Leica's) are
    skipped and checked against its rows."""
    try:
        with open(path, encoding="utf-8-sig", errors="strict") as handle:  # -sig: Excel's BOM
            lines = [line.strip() for line in handle]
    except UnicodeDecodeError:  # a header in a Windows code page ("X (µm)"): numbers are ASCII
        with open(path, encoding="latin-1") as handle:
            lines = [line.strip() for line in handle]
        if any("\x00" in line for line in lines):
            raise InvalidInputError(f"{path}: binary data, not a text point cloud") from None
    rows = [line for line in lines if line and not line.startswith(("#", "//"))]
    if rows and _is_header(rows[0]):
        rows = rows[1:]  # such as "x,y,z" or "X (mm);Y (mm);Z (mm)"
    if rows and (path.suffix.lower() == ".pts" or rows[0].isdigit()):
        rows = _without_pts_counts(path, rows)
    if not rows:
        raise InvalidInputError(f"{path}: holds no points")
    if ";" in rows[0]:
        delimiter = ";"
        rows = [row.replace(",", ".") for row in rows]  # "12,5;3,25;..": decimal commas
    else:
        delimiter = "," if "," in rows[0] else None
    return _loaded_rows(path, rows, delimiter, (0, 1, 2))


def _without_pts_counts(path: Path, rows: list[str]) -> list[str]:
    """``rows`` without a PTS file's lines giving its blocks' point counts, checked against
    the rows under them; as they are when they are not such a file's (a column of numbers)."""
    counts = [row for row in rows if row.isdigit()]
    data = [row for row in rows if not row.isdigit()]  # x y z ... under each count
    if not counts or (data and len(data[0].split()) < 3):
        return rows
    said = sum(int(count) for count in counts)
    if said != len(data):
        raise InvalidInputError(f"{path}: its point counts say {said} points, it holds "
                                f"{len(data)} (a truncated or malformed PTS file)")
    return data


def _loaded_rows(path: Path, rows: list[str], delimiter: str | None, columns) -> np.ndarray:
    """(n, 3) the ``columns`` (x, y, z) of text ``rows``; a row without them, or a value that
    is not a number, raises `InvalidInputError` naming it."""
    try:
        return np.loadtxt(rows, delimiter=delimiter, ndmin=2, usecols=columns)
    except ValueError as exc:
        needed = max(columns) + 1
        short = next((row for row in rows if len(row.split(delimiter)) < needed), None)
        if short is not None:
            n = len(short.split(delimiter))
            raise InvalidInputError(f"{path}: expected rows of x, y, z, but a row has {n} "
                                    f"value{'s' * (n != 1)}: {short[:40]!r}") from exc
        raise InvalidInputError(f"{path}: malformed text point cloud ({exc})") from exc


def _is_header(row: str) -> bool:
    """Whether a text cloud's first row names its columns: a field with a letter that is not a
    number (not "1e-3", "nan" or "inf")."""
    for field in row.replace(",", " ").replace(";", " ").split():
        try:
            float(field)
        except ValueError:
            if any(c.isalpha() for c in field):
                return True
    return False


def check_mesh_path(path: str | os.PathLike, inputs=()) -> Path:
    """Fail before long work when ``path`` cannot take a mesh: bad extension, and as
    `check_output_path`."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_FORMATS:
        raise InvalidInputError(
            f"{path}: unsupported mesh format {suffix or '(none)'!r} "
            f"(use {', '.join(MESH_FORMATS)})"
        )
    return check_output_path(path, inputs)


def check_output_path(path: str | os.PathLike, inputs=()) -> Path:
    """Fail before long work when no file can be written at ``path``: a folder there, a
    missing folder, one where a probe file cannot be written (``os.access`` lets root
    through), or one of the ``inputs`` (paths read) that it would replace."""
    path = Path(path)
    if path.is_dir():
        raise InvalidInputError(f"{path}: is a folder, not a file")
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise InvalidInputError(f"{path}: folder {directory} does not exist")
    for given in inputs:
        if Path(given).exists() and Path(given).resolve() == path.resolve():
            raise InvalidInputError(f"{path}: is also the input, which it would replace")
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InvalidInputError(f"{path}: folder {directory} is not writable "
                                f"({exc.strerror or exc})") from exc
    return path


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file and a rename (no half-written file is
    ever visible), fsynced, with the usual permissions (0666 less the umask)."""
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=directory)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def rounding_to_single(vertices, faces=None) -> float | None:
    """How far (input units) rounding ``vertices`` (n, 3) to float32 moves one at most, when
    that is too far (`SINGLE_PRECISION_TOLERANCE` of their finite ones' diagonal, an edge of
    ``faces`` (f, 3) collapsed, or a value beyond float32's range); None when single precision
    holds them."""
    vertices = np.asarray(vertices, dtype=np.float64)
    finite = np.isfinite(vertices).all(axis=1)
    if not finite.any():
        return None
    with np.errstate(over="ignore"):
        single = vertices.astype(np.float32)
    if not np.isfinite(single[finite]).all():  # beyond float32's range
        return float("inf")
    moved = float(np.abs(single[finite] - vertices[finite]).max())
    diagonal = float(np.linalg.norm(np.ptp(single[finite], axis=0).astype(np.float64)))
    if moved > SINGLE_PRECISION_TOLERANCE * diagonal:
        return moved
    if faces is not None and len(faces):
        faces = np.asarray(faces)
        start, end = faces.ravel(), np.roll(faces, -1, axis=1).ravel()
        for axis in range(3):  # the edges whose ends round to one point, an axis at a time
            column = np.ascontiguousarray(single[:, axis])
            same = column[start] == column[end]
            start, end = start[same], end[same]
        if np.any(vertices[start] != vertices[end]):
            return moved
    return None


def _double_ply(vertices, faces=None) -> bytes:
    """Binary little-endian PLY of ``vertices`` (n, 3) in double precision and triangle
    ``faces`` (f, 3), as trimesh writes them in single precision otherwise."""
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}",
              "property double x", "property double y", "property double z"]
    body = [np.ascontiguousarray(vertices, dtype="<f8").tobytes()]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        packed = np.zeros(len(faces), dtype=[("count", "u1"), ("index", "<i4", (3,))])
        packed["count"], packed["index"] = 3, faces
        body.append(packed.tobytes())
    return "\n".join([*header, "end_header\n"]).encode("ascii") + b"".join(body)


def mesh_data(mesh: trimesh.Trimesh, file_type: str, name: str = "the mesh") -> bytes:
    """``mesh`` as a ``file_type`` (ply, obj, stl, glb) file's bytes: a PLY in double
    precision when single would not hold its vertices (`rounding_to_single`); STL and GLB,
    single precision by their format, then warn (`ReconstructionWarning`, naming ``name``)."""
    file_type = file_type.lower().lstrip(".")
    rounding = (rounding_to_single(mesh.vertices, mesh.faces)  # (OBJ writes 8 decimals)
                if file_type in ("ply", *SINGLE_PRECISION_FORMATS) else None)
    if rounding is not None and file_type == "ply":
        return _double_ply(mesh.vertices, mesh.faces)
    if rounding is not None and file_type in SINGLE_PRECISION_FORMATS:
        warnings.warn(f"{name}: {file_type.upper()} stores single precision, which moves "
                      f"vertices by up to {rounding:.3g} (coordinates up to "
                      f"{float(np.abs(mesh.vertices).max()):.3g}); .ply keeps them",
                      ReconstructionWarning, stacklevel=2)
    data = mesh.export(file_type=file_type)
    return data.encode("utf-8") if isinstance(data, str) else data


def cloud_data(points) -> bytes:
    """A PLY file's bytes of the points (m, 3): single precision when it holds them, as
    `mesh_data`."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if rounding_to_single(points) is not None:
        return _double_ply(points)
    return trimesh.PointCloud(points).export(file_type="ply")


def write_mesh(mesh: trimesh.Trimesh, path: str | os.PathLike) -> Path:
    """Write ``mesh`` in the format given by the extension (`mesh_data`), atomically (temp
    file + rename)."""
    path = check_mesh_path(path)
    return write_bytes_atomic(path, mesh_data(mesh, path.suffix, name=str(path)))


def write_state(path: str | os.PathLike, meta: dict, arrays: dict[str, np.ndarray]) -> Path:
    """Write a fitted state: ``meta`` (JSON-able dict, its ``"format"`` names the kind) and
    named ``arrays`` into one compressed .npz, atomically. No pickles: loading runs no code."""
    buffer = io.BytesIO()
    header = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez_compressed(buffer, meta=header, **arrays)
    return write_bytes_atomic(path, buffer.getvalue())


def read_state(path: str | os.PathLike) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a state written by `write_state`: (meta, arrays), every array read and checked
    (a truncated or damaged archive fails here, not later). Raises `InvalidInputError` with one
    line naming the file and the cause."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such reconstruction state file")
    if not zipfile.is_zipfile(path):  # every .npz is one
        raise InvalidInputError(f"{path}: not a ScanStation reconstruction state (not an "
                                f".npz archive, or a truncated one: `reconstruct --save` "
                                f"writes one)")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
        meta = json.loads(bytes(arrays.pop("meta")).decode())
        if not isinstance(meta, dict):
            raise ValueError("its header is not a JSON object")
    except Exception as exc:  # zip, CRC, JSON and missing-header failures alike: one line
        raise InvalidInputError(
            f"{path}: not a ScanStation reconstruction state ({one_line(exc)})") from exc
    return meta, arrays


def one_line(exc: BaseException) -> str:
    """``exc`` as one line: its type when it says nothing, newlines folded."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, KeyError):
        text = f"missing {text}"
    return text if len(text) <= 200 else text[:197] + "..."
