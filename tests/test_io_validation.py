import warnings

import numpy as np
import pytest
import trimesh

from reconstruct.errors import DegenerateCloudError, InvalidInputError, ReconstructionWarning
from reconstruct.io import (
    check_mesh_path,
    check_output_path,
    cloud_data,
    read_points,
    rounding_to_single,
    write_mesh,
)
from reconstruct.validation import MIN_POINTS, check_points, merge_duplicates

RNG = np.random.default_rng(0)
CLOUD = RNG.normal(size=(50, 3))


@pytest.mark.parametrize("suffix", [".xyz", ".csv", ".npy", ".ply", ".txt"])
def test_read_points_round_trips_every_format(tmp_path, suffix):
    path = tmp_path / f"cloud{suffix}"
    if suffix == ".npy":
        np.save(path, CLOUD)
    elif suffix == ".ply":
        trimesh.PointCloud(CLOUD).export(path)
    elif suffix == ".csv":
        np.savetxt(path, CLOUD, delimiter=",", header="x,y,z", comments="")
    else:
        np.savetxt(path, np.hstack([CLOUD, np.ones((50, 3))]))  # extra columns: normals, colour
    np.testing.assert_allclose(read_points(path), CLOUD, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize(
    ("name", "content"),
    [
        # Leica PTS: each block's point count, then x y z intensity r g b
        ("scan.pts", "2\n0.5 1 2 -1200 10 20 30\n3 4 5 80 1 2 3\n1\n6 7 8 0 0 0 0\n"),
        # a spreadsheet's export where the comma is the decimal mark
        ("export.csv", "X;Y;Z\n0,5;1;2\n3;4;5\n6;7;8\n"),
        ("tabs.xyz", "0.5\t1\t2\n3\t4\t5\n6\t7\t8\n"),
        ("ragged.txt", "0.5 1 2 255 0 0\n3 4 5\n6 7 8 1 0 0 0.5\n"),  # colour on some rows
        ("excel.csv", "\ufeffX (mm);Y;Z\n0,5;1;2\n3;4;5\n6;7;8\n"),  # "CSV UTF-8": a BOM
        ("blocks.pts", "0\n2\n0.5 1 2 0 0 0 0\n3 4 5 0 0 0 0\n1\n6 7 8 0 0 0 0\n"),
        ("semicolon_header.csv", "x;y;z\n0.5,1,2\n3,4,5\n6,7,8\n"),
    ],
)
def test_text_clouds_as_scanners_and_spreadsheets_write_them(tmp_path, name, content):
    path = tmp_path / name
    path.write_text(content, encoding="utf-8")
    np.testing.assert_array_equal(read_points(path), [[0.5, 1, 2], [3, 4, 5], [6, 7, 8]])


def pcd_header(fields, sizes, types, counts, n, data):
    """A PCD v0.7 header (bytes) for ``n`` points."""
    return (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\n"
            f"SIZE {sizes}\nTYPE {types}\nCOUNT {counts}\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n").encode()


def test_pcd_files_as_pcl_writes_them(tmp_path):
    # ascii, a field of COUNT 2 before x; binary, float64 x y z among other fields (PCL's
    # padding "_" and a packed colour)
    ascii_path = tmp_path / "ascii.pcd"
    ascii_path.write_bytes(pcd_header("uv x y z", "4 4 4 4", "F F F F", "2 1 1 1", 3, "ascii")
                           + b"9 9 0.5 1 2\n9 9 3 4 5\n9 9 6 7 8\n")
    expected = [[0.5, 1, 2], [3, 4, 5], [6, 7, 8]]
    np.testing.assert_array_equal(read_points(ascii_path), expected)
    dtype = np.dtype([("_", "<u1", (3,)), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                      ("rgb", "<u4")])
    rows = np.zeros(3, dtype)
    rows["x"], rows["y"], rows["z"] = np.array(expected).T
    binary_path = tmp_path / "binary.pcd"
    binary_path.write_bytes(pcd_header("_ x y z rgb", "1 8 8 8 4", "U F F F U", "3 1 1 1 1",
                                       3, "binary") + rows.tobytes())
    np.testing.assert_array_equal(read_points(binary_path), expected)
    # a truncated file, a compressed one, one without coordinates
    (tmp_path / "short.pcd").write_bytes(binary_path.read_bytes()[:-10])
    (tmp_path / "packed.pcd").write_bytes(pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 3,
                                                     "binary_compressed") + b"\x00" * 20)
    (tmp_path / "flat.pcd").write_bytes(pcd_header("u v", "4 4", "F F", "1 1", 1, "ascii")
                                        + b"1 2\n")
    (tmp_path / "empty.pcd").write_bytes(pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 0,
                                                    "ascii"))
    for name, message in [("short.pcd", "header says 3 points, it holds 2"),
                          ("packed.pcd", "'binary_compressed' is not read"),
                          ("flat.pcd", "fields are u v, without x, y and z"),
                          ("empty.pcd", "holds no points")]:
        with pytest.raises(InvalidInputError, match=message):
            read_points(tmp_path / name)


def test_a_text_file_shorter_or_longer_than_its_header_says_is_refused(tmp_path):
    rows = "".join(f"{i} {i % 7} {i % 5}\n" for i in range(40))
    for name, header, message in [
            ("short.ply", "element vertex 60", "header says 60 vertices, it holds 40"),
            ("huge.ply", "element vertex 1000000000000", "header says 1000000000000 vertices"),
            ("negative.ply", "element vertex -5", "header says -5 vertices")]:
        (tmp_path / name).write_text(f"ply\nformat ascii 1.0\n{header}\nproperty float x\n"
                                     f"property float y\nproperty float z\nend_header\n{rows}")
        with pytest.raises(InvalidInputError, match=message):
            read_points(tmp_path / name)
    whole = tmp_path / "whole.ply"
    whole.write_text("ply\nformat ascii 1.0\nelement vertex 40\nproperty float x\n"
                     f"property float y\nproperty float z\nend_header\n{rows}")
    assert read_points(whole).shape == (40, 3)
    short = tmp_path / "short.pcd"
    short.write_bytes(pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 60, "ascii")
                      + rows.encode())
    with pytest.raises(InvalidInputError, match="header says 60 points, it holds 40 rows"):
        read_points(short)


def test_an_npy_of_other_values_than_real_numbers_is_refused(tmp_path):
    for name, values in [("text.npy", np.full((20, 3), "a")),
                         ("complex.npy", np.ones((20, 3)) * (1 + 2j))]:
        np.save(tmp_path / name, values)
        with pytest.raises(InvalidInputError, match="not real numbers"):
            read_points(tmp_path / name)


def test_a_spreadsheets_header_in_a_windows_code_page_is_read(tmp_path):
    path = tmp_path / "export.csv"
    path.write_bytes("X (µm);Y (µm);Z (µm)\n0,5;1;2\n3;4;5\n".encode("cp1252"))
    np.testing.assert_array_equal(read_points(path), [[0.5, 1, 2], [3, 4, 5]])


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.ply", b"", "file is empty"),
        ("garbage.ply", b"not a ply at all\n1 2 3\n", "malformed PLY"),
        (
            "truncated.ply",
            b"ply\nformat ascii 1.0\nelement vertex 10\nproperty float x\n",
            "cannot read PLY",
        ),
        ("words.xyz", b"a b c\nd e f\n", "malformed text"),
        ("two_columns.csv", b"1,2\n3,4\n", "expected rows of x, y, z"),
        ("short_row.xyz", b"1 2 3\n4 5\n", "a row has 2 values: '4 5'"),
        ("one_column.xyz", b"1\n2.5\n3\n", "a row has 1 value: '1'"),
        ("renamed.xyz", b"LASF\x01\x00\xff\xfe binary", "binary data, not a text point cloud"),
        ("bad_first_row.xyz", b"1..5 2 3\n4 5 6\n", "could not convert string '1..5'"),
        ("count_only.pts", b"5\n", "its point counts say 5 points, it holds 0"),
        ("truncated.pts", b"3\n1 2 3 9\n4 5 6 9\n", "its point counts say 3 points, it holds 2"),
        ("cloud.las", b"xx", "unsupported point cloud format"),
    ],
)
def test_bad_files_give_one_line_errors(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(InvalidInputError, match=message) as info:
        read_points(path)
    assert "\n" not in str(info.value)
    assert name in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(InvalidInputError, match="no such file"):
        read_points(tmp_path / "nope.ply")


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl", ".glb"])
def test_write_mesh_by_extension(tmp_path, suffix):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    path = write_mesh(mesh, tmp_path / f"m{suffix}")
    loaded = trimesh.load(path, force="mesh")
    assert len(loaded.faces) == len(mesh.faces)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "no temp file left"


def _far_sphere() -> trimesh.Trimesh:
    """A 150 mm sphere, in metres, 5,000 km from the origin (map coordinates): float32 rounds
    its vertices to half a metre."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.075)
    mesh.apply_translation([5.0e6, 5.0e6, 120.0])
    return mesh


def _header(path) -> bytes:
    return path.read_bytes().split(b"end_header")[0]


def test_a_mesh_far_from_the_origin_is_written_in_double_precision(tmp_path):
    mesh = _far_sphere()
    path = write_mesh(mesh, tmp_path / "far.ply")
    assert b"property double x" in _header(path)
    exact = trimesh.load(path, process=False)
    assert np.array_equal(exact.vertices, mesh.vertices)
    assert np.array_equal(exact.faces, mesh.faces)
    merged = trimesh.load(path)  # a reader that merges vertices finds the same closed mesh
    assert merged.is_watertight and merged.euler_number == 2
    assert merged.area == pytest.approx(mesh.area)


def test_a_mesh_near_the_origin_stays_single_precision(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=75.0)
    mesh.apply_translation([300.0, -200.0, 120.0])  # a scan station's millimetres
    path = write_mesh(mesh, tmp_path / "near.ply")
    assert b"property float x" in _header(path)
    assert np.allclose(trimesh.load(path, process=False).vertices, mesh.vertices, atol=1e-4)


def test_values_single_precision_cannot_hold_need_double():
    far = _far_sphere().vertices.copy()
    far[0] = np.nan  # a NaN row does not hide the others' rounding
    assert rounding_to_single(far) > 0.01
    assert rounding_to_single([[1e39, 0.0, 0.0], [1.001e39, 1.0, 1.0]]) == np.inf  # overflows
    assert rounding_to_single(np.full((3, 3), np.nan)) is None


def test_an_edge_that_single_precision_collapses_needs_double():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=75.0)
    vertices, faces = mesh.vertices.copy(), mesh.faces
    vertices[faces[0, 0]] = vertices[faces[0, 0]].astype(np.float32)  # exact in float32
    vertices[faces[0, 1]] = vertices[faces[0, 0]] * (1 + 1e-9)  # well within its ulp
    assert rounding_to_single(mesh.vertices, faces) is None
    assert rounding_to_single(vertices, faces) is not None


@pytest.mark.parametrize("suffix", [".stl", ".glb"])
def test_single_precision_formats_warn_far_from_the_origin(tmp_path, suffix):
    with pytest.warns(ReconstructionWarning, match=f"{suffix[1:].upper()} stores single "
                                                    "precision.*.ply keeps them"):
        write_mesh(_far_sphere(), tmp_path / f"far{suffix}")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_mesh(trimesh.creation.icosphere(subdivisions=1), tmp_path / f"near{suffix}")


def test_a_cloud_far_from_the_origin_keeps_its_points(tmp_path):
    points = _far_sphere().vertices
    path = tmp_path / "cloud.ply"
    path.write_bytes(cloud_data(points))
    assert np.array_equal(read_points(path), points)
    near = tmp_path / "near.ply"
    near.write_bytes(cloud_data(points - points.mean(axis=0)))
    assert b"property float x" in _header(near)


def test_mesh_path_checked_before_work(tmp_path):
    with pytest.raises(InvalidInputError, match="unsupported mesh format"):
        check_mesh_path(tmp_path / "m.xyz")
    with pytest.raises(InvalidInputError, match="does not exist"):
        check_mesh_path(tmp_path / "missing" / "m.ply")
    (tmp_path / "folder.ply").mkdir()
    with pytest.raises(InvalidInputError, match="is a folder, not a file"):
        check_mesh_path(tmp_path / "folder.ply")
    cloud = tmp_path / "cloud.ply"
    cloud.write_text("ply")
    with pytest.raises(InvalidInputError, match="is also the input, which it would replace"):
        check_mesh_path(tmp_path / "." / "cloud.ply", inputs=[cloud])
    assert check_mesh_path(tmp_path / "mesh.ply", inputs=[cloud]) == tmp_path / "mesh.ply"
    assert not list(tmp_path.glob(".mesh.ply.*"))  # the probe is gone


def test_an_output_folder_is_written_to_not_asked(tmp_path, monkeypatch):
    import tempfile

    def refused(*args, **kwargs):  # as a read-only mount answers root, whom os.access passes
        raise PermissionError(13, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", refused)
    with pytest.raises(InvalidInputError, match="is not writable .Read-only file system"):
        check_output_path(tmp_path / "state.npz")


def test_a_far_stray_point_does_not_make_a_cloud_collinear():
    from reconstruct.errors import DegenerateCloudError

    far = np.vstack([CLOUD, [[1e9, 0.0, 0.0]]])  # a depth camera's invalid value
    assert check_points(far).shape == far.shape
    line = np.column_stack([np.linspace(0, 1, 50)] * 3)
    with pytest.raises(DegenerateCloudError, match="collinear"):
        check_points(np.vstack([line, [[0.0, 1e9, 0.0]]]))


def test_coordinates_whose_distances_overflow_are_refused():
    with pytest.raises(InvalidInputError, match="distances between the points overflow"):
        check_points(CLOUD * 1e298)
    assert check_points(CLOUD * 1e140).shape == CLOUD.shape  # large, and still measurable


def test_check_points_drops_nonfinite_with_warning():
    cloud = CLOUD.copy()
    cloud[3, 1] = np.nan
    cloud[7, 2] = np.inf
    with pytest.warns(ReconstructionWarning, match="dropped 2 of 50 points with NaN"):
        clean = check_points(cloud)
    assert clean.shape == (48, 3) and np.isfinite(clean).all()


def test_check_points_merges_duplicates_with_warning():
    cloud = np.vstack([CLOUD, CLOUD[:5]])
    with pytest.warns(ReconstructionWarning, match="merged 5 duplicate points"):
        clean = check_points(cloud)
    np.testing.assert_array_equal(clean, CLOUD)


def plane_sample(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(0, 100, (n, 2)), rng.normal(0, 0.5, n)]


def test_check_points_merges_near_duplicates_left_by_round_off():
    cloud = plane_sample(2000)
    copy = cloud[:300] + np.random.default_rng(1).normal(0, 1e-9, (300, 3))
    with pytest.warns(ReconstructionWarning, match="merged 300 duplicate points"):
        clean = check_points(np.vstack([cloud, copy]))
    np.testing.assert_array_equal(clean, cloud)


def test_far_outliers_do_not_make_every_point_a_duplicate():
    cloud = plane_sample(2000)
    with_outliers = np.vstack([cloud, [[1e6, 1e6, 1e6], [-1e6, 0.0, 0.0]]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(check_points(with_outliers), with_outliers)


@pytest.mark.parametrize("apart", [1e-3, 0.01])  # of the nearest-neighbour spacing (1.1)
def test_check_points_merges_a_cloud_with_its_moved_copy(apart):
    cloud = plane_sample(2000)
    copy = cloud + np.random.default_rng(1).normal(0, apart, cloud.shape)
    with pytest.warns(ReconstructionWarning, match="into their twins"):
        clean = check_points(np.vstack([cloud, copy]))
    assert len(clean) < 2020  # (a copy nearer another point than its own stays)
    np.testing.assert_array_equal(clean[:2000], cloud)


def test_checked_points_are_checked_again_unchanged():
    cloud = plane_sample(2000)  # doubled 1e-9 apart, and the two doubled 0.01 apart
    doubled = np.vstack([cloud, cloud + 1e-9])
    twice = np.vstack([doubled, doubled + 0.01])
    with pytest.warns(ReconstructionWarning, match="merged"):
        clean = check_points(twice)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(check_points(clean), clean)


def lines_sample(seed=0):
    """60 scan lines 10 apart, 200 points thrown at random along each."""
    rng = np.random.default_rng(seed)
    return np.vstack([np.c_[np.sort(rng.uniform(0, 200, 200)), np.full(200, 10.0 * j),
                            0.01 * rng.normal(size=200)] for j in range(60)])


def two_densities(seed=0):
    """A plane with a patch sampled at a seventh of its spacing (30 % of the points)."""
    rng = np.random.default_rng(seed)
    return np.vstack([np.c_[rng.uniform(0, 100, (7000, 2)), np.zeros(7000)],
                      np.c_[rng.uniform(0, 9.4, (3000, 2)), np.zeros(3000)]])


def far_outliers(share, seed=0):
    rng = np.random.default_rng(seed)
    n = int(4000 * share / (1 - share))
    return np.vstack([plane_sample(4000, seed), rng.uniform(-1e6, 1e6, (n, 3))])


@pytest.mark.parametrize("cloud", [
    np.c_[np.random.default_rng(2).uniform(0, 100, (20000, 2)), np.zeros(20000)],
    plane_sample(20000, seed=2), lines_sample(), two_densities(), far_outliers(0.6),
    plane_sample(2000) * 1e160, plane_sample(2000) * 1e-170,
    np.vstack([plane_sample(2000) * 1e-170, [[1.0, 1.0, 1.0]]]),
], ids=["noise-free plane", "noisy plane", "random along lines", "two densities",
        "60 % far outliers", "huge coordinates", "tiny coordinates", "tiny spread"])
def test_an_ordinary_sample_has_no_twins_to_merge(cloud):
    # twins (a point's nearest five times nearer than its next): a Poisson sample of a plane
    # has 4 %, points at random along lines 19 %, against TWIN_SHARE
    kept, merged = merge_duplicates(cloud)
    assert len(kept) == len(cloud) and merged == ""


def test_many_points_at_one_place_merge_at_once():
    cloud = plane_sample(20000)  # (invalid pixels saved at the origin: every pair listed
    with_zeros = np.vstack([cloud, np.zeros((30000, 3))])  # took 26 GB)
    with pytest.warns(ReconstructionWarning, match="merged 29999 duplicate points"):
        assert len(check_points(with_zeros)) == 20001


def test_a_tiny_cloud_is_never_merged_by_chance():
    for seed in range(300):
        cloud = np.c_[np.random.default_rng(seed).uniform(0, 1, (20, 2)), np.zeros(20)]
        assert len(merge_duplicates(cloud)[0]) == 20


def test_clean_cloud_passes_silently():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(check_points(CLOUD), CLOUD)


@pytest.mark.parametrize(
    ("cloud", "error", "message"),
    [
        (np.empty((0, 3)), InvalidInputError, "empty"),
        (np.zeros((10, 2)), InvalidInputError, r"shape \(n, 3\)"),
        (np.full((30, 3), np.nan), InvalidInputError, "all 30 points"),
        (CLOUD[: MIN_POINTS - 1], InvalidInputError, f"needs at least {MIN_POINTS}"),
        (np.outer(np.arange(40.0), [1, 2, 3]), DegenerateCloudError, "collinear"),
        ([["a", "b", "c"]], InvalidInputError, "not numeric"),
    ],
)
def test_check_points_rejects(cloud, error, message):
    with pytest.raises(error, match=message):
        check_points(cloud)
