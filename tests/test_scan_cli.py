"""`scanstation scan / replay / calibrate` on the simulated station: files, reports, errors."""

import dataclasses
import json
import subprocess
import sys
import uuid

import numpy as np
import pytest
import trimesh

from capture.cli import main
from capture.plan import ScanPlan

SMALL_CAMERA = "sim://camera?width=320&height=200"


def sim_urls():
    station = f"cli-{uuid.uuid4().hex[:8]}"
    return ["--camera", f"{SMALL_CAMERA}&station={station}",
            "--turntable", f"sim://turntable?instant=1&station={station}"]


@pytest.fixture(scope="module")
def scanned(tmp_path_factory, fast_params):
    """A 6-view simulated scan through the CLI (a plan file keeps the networks tiny)."""
    tmp = tmp_path_factory.mktemp("cli")
    plan = tmp / "plan.json"
    plan.write_text(ScanPlan.turn(6, frames_per_view=2, settle_s=0.0,
                                  reconstruction=fast_params).to_json())
    out = tmp / "scan"
    code = main(["scan", *sim_urls(), "--plan", str(plan), "-o", str(out), "--workers", "1"])
    return code, out


def test_scan_writes_recording_mesh_and_report(scanned, capsys):
    code, out = scanned
    assert code == 0
    assert {p.name for p in out.iterdir()} >= {"recording.mcap", "mesh.ply", "cloud.ply",
                                               "scan.json", "engine"}
    report = json.loads((out / "scan.json").read_text())
    assert report["state"] == "done" and report["views_done"] == 6
    assert report["plan"]["angles"] == [0, 60, 120, 180, 240, 300]
    assert report["calibration"]["format"] == "scanstation-calibration/1"
    assert report["station"]["simulated"] is True
    quality = report["quality"]
    assert 0 < quality["completeness_visible"] <= 1 and quality["denoise_ratio"] > 0
    assert quality["tau_mm"] == pytest.approx(0.01 * quality["object_size_mm"])
    assert report["mesh"]["final"] and report["mesh"]["faces"] > 1000
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert len(mesh.faces) == report["mesh"]["faces"]
    # The merged, calibrated cloud the mesh was fitted to: on the mesh's object, in mm.
    cloud = trimesh.load(out / "cloud.ply", process=False)
    assert len(cloud.vertices) == report["mesh"]["points"]
    assert np.abs(cloud.vertices.mean(axis=0) - mesh.vertices.mean(axis=0)).max() < 10.0


def test_replay_command_reproduces_the_mesh(scanned, tmp_path, capsys):
    _, out = scanned
    assert main(["replay", str(out), "-o", str(tmp_path / "again"), "--workers", "1"]) == 0
    assert "done: all 6 views captured" in capsys.readouterr().out
    original = trimesh.load(out / "mesh.ply", process=False)
    again = trimesh.load(tmp_path / "again" / "mesh.ply", process=False)
    np.testing.assert_array_equal(again.vertices, original.vertices)


def test_remesh_takes_a_scan_folder(scanned, tmp_path, capsys):
    _, out = scanned
    for source in (out, out / "engine"):
        mesh = tmp_path / f"{source.name}.ply"
        assert main(["--quiet", "remesh", str(source), "--lam", "3", "-o", str(mesh)]) == 0
        assert len(trimesh.load(mesh, process=False).faces) > 1000
    errors = {(str(out), "--spacing", "2"): "--spacing: a scan re-meshes with --lam and --depth "
                                             "only",
              (str(tmp_path),): "a folder without a scan's reconstruction",
              (str(out / "mesh.ply"),): "not a ScanStation reconstruction state (not an .npz"}
    for args, message in errors.items():
        assert main(["remesh", *args, "-o", str(tmp_path / "m.ply")]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("scanstation: error: ") and message in err[-1]


def test_capture_only_scan_shows_progress(tmp_path, capsys):
    out = tmp_path / "raw"
    code = main(["scan", *sim_urls(), "--views", "3", "--frames", "1", "--settle", "0",
                 "--no-reconstruction", "-o", str(out)])
    captured = capsys.readouterr()
    assert code == 0
    assert "view 3/3" in captured.err and "done: all 3 views captured" in captured.out
    assert (out / "recording.mcap").is_file() and not (out / "mesh.ply").exists()
    assert json.loads((out / "scan.json").read_text())["quality"] is None


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["scan", "--views", "0"], "views must be a whole number in [1, 3600], got 0"),
        (["scan", "--camera", "oak://", "--object", "vase"], "--object needs the simulated"),
        (["scan", "--object", "no-such-object", "--no-reconstruction"],
         "object 'no-such-object': no such file"),
        (["scan", "--object", "", "--no-reconstruction"], "object '': an empty name"),
        (["replay", "missing.mcap"], "missing.mcap: no such recording"),
        (["scan", "--camera", "sim://camera", "--turntable", "sim://turntable",
          "--calibration", "nowhere.json"], "cannot read calibration nowhere.json"),
    ],
)
def test_bad_input_is_one_line_and_exit_1(args, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("scanstation: error: ") and message in err[-1]


def test_unwritable_output_fails_before_the_scan(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    assert main(["scan", *sim_urls(), "-o", str(tmp_path / "file" / "scan")]) == 1
    assert "is not writable" in capsys.readouterr().err


def test_calibrate_the_simulated_station(tmp_path, capsys):
    out = tmp_path / "calibration.json"
    assert main(["calibrate", *sim_urls()[2:], "--views", "8", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    distance, angle = (float(x) for x in
                       printed.split("true axis: ")[1].replace("°", "").split(" mm, "))
    assert distance < 1.0 and angle < 0.5
    assert json.loads(out.read_text())["format"] == "scanstation-calibration/1"


def test_entry_point_runs_as_a_program():
    result = subprocess.run([sys.executable, "-m", "capture.cli", "scan", "--help"],
                            capture_output=True, text=True, check=True)
    for option in ("--camera", "--turntable", "--views", "--object", "--output", "--resume"):
        assert option in result.stdout


def test_plan_file_round_trip(tmp_path, fast_params):
    plan = dataclasses.replace(ScanPlan.turn(4), reconstruction=fast_params)
    assert ScanPlan.from_json(plan.to_json()) == plan


def test_scan_help_names_every_built_in_object():
    from capture.commands.scan import BUILT_IN_OBJECTS
    from sim.objects import BUILT_IN

    assert set(BUILT_IN_OBJECTS) == set(BUILT_IN)
