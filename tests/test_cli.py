"""The `scanstation` command line: outputs, one-line errors, non-zero exits, no tracebacks."""

import subprocess
import sys

import numpy as np
import pytest
import trimesh
from surface_checks import sphere_cloud

from capture.cli import main
from reconstruct.pipeline import SurfaceReconstructor
from reconstruct.validation import ATLAS_POINTS


def _plane(path, n=500, seed=0):
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(-1, 1, (n, 2)), rng.normal(0, 0.01, n)])
    np.savetxt(path, points)
    return path


def test_reconstruct_then_remesh(tmp_path, capsys):
    cloud = _plane(tmp_path / "plane.xyz")
    out = tmp_path / "mesh.obj"
    state = tmp_path / "state.npz"
    args = ["--quiet", "reconstruct", str(cloud), "-o", str(out), "--max-layers", "1"]
    assert main([*args, "--max-neurons", "6", "--save", str(state)]) == 0
    mesh = trimesh.load(out, force="mesh")
    assert len(mesh.faces) > 100
    again = tmp_path / "again.stl"
    assert main(["--quiet", "remesh", str(state), "-o", str(again), "--lam", "4"]) == 0
    assert len(trimesh.load(again, force="mesh").faces) > 100
    areas = {}
    for extend in ("0", "border"):
        grown = tmp_path / f"extend-{extend}.ply"
        assert main(["--quiet", "remesh", str(state), "-o", str(grown), "--extend", extend]) == 0
        areas[extend] = trimesh.load(grown, force="mesh").area
    assert areas["0"] < areas["border"]


def test_quiet_keeps_the_warnings(tmp_path, capsys):
    cloud = _plane(tmp_path / "plane.xyz")
    with open(cloud, "a") as handle:
        handle.write("nan 0 0\n")
    out = tmp_path / "mesh.ply"
    args = ["--quiet", "reconstruct", str(cloud), "-o", str(out), "--max-layers", "1"]
    assert main([*args, "--max-neurons", "6"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == ["warning: dropped 1 of 501 points with NaN or infinite coordinates"]


def test_extend_option_rejects_a_bad_value(tmp_path, capsys):
    cloud = _plane(tmp_path / "plane.xyz")
    with pytest.raises(SystemExit) as exit_:
        main(["reconstruct", str(cloud), "-o", str(tmp_path / "m.ply"), "--extend", "far"])
    assert exit_.value.code == 2
    assert "expected auto, border or a number >= 0, got 'far'" in capsys.readouterr().err


def test_max_points_option(tmp_path, capsys):
    cloud = _plane(tmp_path / "plane.xyz")
    out = tmp_path / "mesh.ply"
    fast = ["--max-layers", "1", "--max-neurons", "6"]
    assert main(["reconstruct", str(cloud), "-o", str(out), *fast, "--max-points", "300"]) == 0
    assert "fitting 300 of the" in capsys.readouterr().err
    for bad in ("few", "50"):
        with pytest.raises(SystemExit) as exit_:
            main(["reconstruct", str(cloud), "-o", str(out), "--max-points", bad])
        assert exit_.value.code == 2
        assert f"expected all or a whole number >= 100, got '{bad}'" in capsys.readouterr().err


def test_atlas_points_option(tmp_path, capsys):
    # a closed cloud goes to the atlas, which charts the N points asked of a denser cloud
    # (--max-points is one chart's: the atlas's was left at its 20,000 without a word)
    cloud = tmp_path / "sphere.npy"
    np.save(cloud, sphere_cloud(1500))
    out = tmp_path / "mesh.ply"
    fast = ["--max-layers", "1", "--max-neurons", "6"]
    state = tmp_path / "state.npz"
    assert main(["reconstruct", str(cloud), "-o", str(out), *fast, "--atlas-points", "900",
                 "--save", str(state)]) == 0
    assert "atlas of 900 of the 1500 points" in capsys.readouterr().err
    # a fit's parameter, not the state's: a build without it reads the state
    assert SurfaceReconstructor.load(state).atlas_points == ATLAS_POINTS
    with pytest.raises(SystemExit) as exit_:
        main(["reconstruct", str(cloud), "-o", str(out), "--atlas-points", "50"])
    assert exit_.value.code == 2
    assert "expected all or a whole number >= 100, got '50'" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "file is empty"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n", "PLY"),
        (b"nan nan nan\n" * 30, "NaN or infinite"),
        ("".join(f"{i} {2 * i} {3 * i}\n" for i in range(100)).encode(), "collinear"),
        (bytes(range(256)) * 20, "binary data, not a text point cloud"),
        (b"0.1 0.2 0.3\n0.5 0.1 0.9\n0.3 0.3 0.1\n", "needs at least"),  # too few points
        (b"1 2 3\n" * 300, "needs at least"),  # one point, 300 times
        (None, "is a directory"),
        ("missing", "no such file"),
    ],
)
def test_bad_input_is_one_line_and_nonzero(tmp_path, content, message):
    suffix = ".ply" if content in (b"", None) or str(content).startswith("b'ply") else ".xyz"
    path = tmp_path / f"bad{suffix}"
    if content is None:
        path.mkdir()
    elif isinstance(content, bytes):
        path.write_bytes(content)
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "capture.cli",
            "reconstruct",
            str(path),
            "-o",
            str(tmp_path / "m.ply"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0
    error_lines = [
        line for line in result.stderr.splitlines() if line.startswith("scanstation: error")
    ]
    assert len(error_lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    if message:
        assert message in error_lines[0]
    assert not (tmp_path / "m.ply").exists()


def test_unwritable_output_fails_before_work(tmp_path, capsys):
    cloud = _plane(tmp_path / "plane.xyz")
    code = main(["reconstruct", str(cloud), "-o", str(tmp_path / "nowhere" / "m.ply")])
    assert code == 1
    assert "does not exist" in capsys.readouterr().err


def test_every_output_is_checked_before_the_fit(tmp_path, capsys, monkeypatch):
    from reconstruct.pipeline import SurfaceReconstructor

    def no_fit(*args, **kwargs):
        raise AssertionError("fitted before its outputs were checked")

    monkeypatch.setattr(SurfaceReconstructor, "fit", no_fit)
    cloud = _plane(tmp_path / "plane.xyz")
    before = cloud.read_bytes()
    (tmp_path / "folder.ply").mkdir()
    for extra, said in [(["-o", str(tmp_path / "folder.ply")], "is a folder, not a file"),
                        (["-o", str(tmp_path / "m.ply"), "--save",
                          str(tmp_path / "nowhere" / "state.npz")], "does not exist"),
                        (["-o", str(tmp_path / "m.ply"), "--save", str(cloud)],
                         "is also the input")]:
        assert main(["reconstruct", str(cloud), *extra]) == 1
        assert said in capsys.readouterr().err
    assert cloud.read_bytes() == before


def test_devices_lists_backends(capsys):
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    for scheme in ("grbl://", "sim://", "oak://"):
        assert scheme in out


def test_the_simulated_turntable_serves_another_process_on_a_pty(tmp_path):
    import drivers

    link = tmp_path / "ttyGRBL"
    server = subprocess.Popen(
        [sys.executable, "-m", "capture.cli", "-q", "simulate-turntable", "--instant",
         "--link", str(link)], stdout=subprocess.PIPE, text=True)
    try:
        banner = server.stdout.readline()
        assert f"open grbl://{link}" in banner
        with drivers.open_turntable(f"grbl://{link}") as table:  # the production driver
            table.move_to(45)
            assert table.angle == 45
    finally:
        server.terminate()
        assert server.wait(10) == 0
    assert not link.exists()  # the link goes with the simulator


def test_the_atlas_can_be_asked_for(tmp_path, capsys):
    # a closed object with walls thinner than the noise is one open sheet to one chart (said);
    # --atlas always fits the atlas, which joins such walls closed
    rng = np.random.default_rng(0)
    plate = np.column_stack([rng.uniform(-1, 1, (600, 2)), rng.normal(0, 0.01, 600)])
    np.savetxt(tmp_path / "plate.xyz", plate)
    args = ["reconstruct", str(tmp_path / "plate.xyz"), "-o", str(tmp_path / "m.ply"),
            "--max-layers", "1", "--max-neurons", "4"]
    assert main([*args, "--atlas", "always"]) == 0
    assert "fitting an atlas of charts: asked for" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:
        main([*args, "--atlas", "sometimes"])
    assert refused.value.code == 2
    assert "invalid choice: 'sometimes'" in capsys.readouterr().err


def test_a_cloud_in_two_pieces_meshes_both(tmp_path, capsys):
    # One chart would embed the largest piece only: the cloud goes to the atlas (said in one
    # line), which meshes both: no piece of the data is dropped.
    rng = np.random.default_rng(0)
    big = np.column_stack([rng.uniform(-1, 1, (600, 2)), rng.normal(0, 0.01, 600)])
    small = np.column_stack([rng.uniform(3, 4, (150, 2)), rng.normal(0, 0.01, 150)])
    np.savetxt(tmp_path / "two.xyz", np.vstack([big, small]))
    out = tmp_path / "m.ply"
    args = ["reconstruct", str(tmp_path / "two.xyz"), "-o", str(out), "--max-layers", "1",
            "--max-neurons", "4"]
    assert main(args) == 0
    assert ("fitting an atlas of charts: its neighbourhood graph is in 2 pieces, the largest 600 "
            "of 750 points") in capsys.readouterr().err
    vertices = trimesh.load(out, force="mesh").vertices
    in_small = (vertices[:, :2] > 2.0).all(axis=1)
    assert 0.05 < in_small.mean() < 0.5  # both pieces meshed
    assert (vertices[~in_small, :2] < 1.2).all()  # each piece where its points are
