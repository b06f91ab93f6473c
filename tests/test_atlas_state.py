"""A fitted atlas saves and loads: all charts' ONNX maps, the partition and the signs; the loaded
one re-meshes without torch to the same mesh; a damaged file fails in one line."""

import io
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import trimesh
from surface_checks import sphere_cloud

from capture.cli import main
from reconstruct.atlas import AtlasReconstructor
from reconstruct.chart_sides import uncharted_reach
from reconstruct.errors import InvalidInputError
from reconstruct.faithfulness import residual_kurtosis, sampled_kurtosis
from reconstruct.io import read_state
from reconstruct.pipeline import SurfaceReconstructor


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    model = SurfaceReconstructor(atlas="always").fit(sphere_cloud())
    model.remesh(lam=2.0)
    path = model.save(tmp_path_factory.mktemp("atlas") / "sphere.npz")
    return model, path


def same_mesh(a, b):
    assert len(a.vertices) == len(b.vertices) and len(a.faces) == len(b.faces)
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-9)
    np.testing.assert_array_equal(a.faces, b.faces)


def test_a_loaded_atlas_remeshes_to_the_same_mesh(saved):
    model, path = saved
    loaded = SurfaceReconstructor.load(path)
    assert len(loaded.atlas_.charts_) == len(model.atlas_.charts_) >= 2
    assert loaded.lam == 2.0 and loaded.atlas_reason_ == model.atlas_reason_
    assert all(("multidepth", depth, 8) in chart._boundary_cache  # saved: no sampling on load
               for chart in loaded.atlas_.charts_ for depth in (1, 2, 3))
    same_mesh(loaded.remesh(), model.mesh_)
    assert loaded.atlas_._sdf.n_changed_ == 0  # the saved join grid and mesh were used
    assert loaded.mesh_.is_watertight and loaded.mesh_.euler_number == 2
    fresh = SurfaceReconstructor.load(path)
    del fresh.atlas_._sdf  # the join evaluated afresh from the charts' maps gives it too
    same_mesh(fresh.remesh(), model.mesh_)
    assert fresh.atlas_._sdf.n_changed_ == len(fresh.atlas_.samples_)
    same_mesh(loaded.remesh(lam=3.0, depth=3), model.remesh(lam=3.0, depth=3))
    atlas = AtlasReconstructor.load(path)  # the atlas alone reads the same file
    np.testing.assert_array_equal(atlas.signs_, model.atlas_.signs_)
    assert atlas.noise_ == model.atlas_.noise_ > 0  # (what counts as data left out)
    for before, after in zip(model.atlas_.details_, atlas.details_, strict=True):
        np.testing.assert_array_equal(before.residuals_, after.residuals_)
        np.testing.assert_array_equal(before.points_, after.points_)
        assert (before.width, before.variance_, before.shape_) == (
            after.width, after.variance_, after.shape_)
    for before, after in zip(model.atlas_.chart_points_, atlas.chart_points_, strict=True):
        np.testing.assert_array_equal(before, after)
    alone = AtlasReconstructor.load(model.atlas_.save(path.with_name("alone.npz")))
    same_mesh(alone.remesh(), model.mesh_)  # and writes its own
    wrapped = SurfaceReconstructor.load(path.with_name("alone.npz"))  # which the whole reads
    assert (wrapped.lam, wrapped.depth) == (model.lam, model.depth) == (3.0, 3)  # re-meshed last
    assert "AtlasReconstructor.save" in wrapped.atlas_reason_
    assert wrapped.max_points == SurfaceReconstructor().max_points  # a training parameter
    same_mesh(wrapped.remesh(), model.mesh_)
    model.remesh(lam=2.0)  # as the other tests expect it


def test_a_state_saved_before_the_noise_was_measured_keeps_its_rule(saved, tmp_path):
    # its uncharted points were those a spacing from every sample, whatever the noise
    model, _ = saved
    path = model.atlas_.save(tmp_path / "atlas.npz")
    meta, arrays = read_state(path)
    assert meta.pop("noise") > 0
    old = AtlasReconstructor.from_state(meta, arrays)
    assert "noise_" not in vars(old)
    assert old._uncharted_reach() == uncharted_reach(old.decomposition_.spacing_)
    same_mesh(old.remesh(), AtlasReconstructor.load(path).remesh())


def test_a_state_saved_before_the_residual_detail_joins_its_charts_as_they_are(saved, tmp_path):
    model, _ = saved
    path = model.atlas_.save(tmp_path / "atlas.npz")
    meta, arrays = read_state(path)
    del meta["detail"], arrays["detail_residuals"]
    old = AtlasReconstructor.from_state(meta, arrays)
    assert "details_" not in vars(old)
    parts = old._chart_parts()
    for part, samples in zip(parts, old._detailed_samples(parts), strict=True):
        assert samples is part.samples
    assert old.remesh(lam=2.5).is_watertight
    # (the sphere's charts hold their shape: a chart that smoothed one would move its samples)
    new = AtlasReconstructor.load(path)
    new.details_[0].shape_ = new.details_[0].variance_
    parts = new._chart_parts()
    moved = new._detailed_samples(parts)[0]
    assert moved is not parts[0].samples and not np.array_equal(moved, parts[0].samples)


def test_a_state_whose_residuals_do_not_fit_its_charts_is_refused(saved, tmp_path):
    model, _ = saved
    meta, arrays = read_state(model.atlas_.save(tmp_path / "atlas.npz"))
    arrays["detail_residuals"] = arrays["detail_residuals"][:-1]
    with pytest.raises(ValueError, match="residuals"):
        AtlasReconstructor.from_state(meta, arrays)


def test_a_loaded_atlas_keeps_the_saved_probe(saved):
    """A loaded atlas turns its charts' folded flaps by the saved probe, not by one built again
    from the samples it was saved with (hook 22k re-meshed at λ 2 straight after loading:
    1,176 of 36,432 vertices differed from the atlas saved, and from the loaded atlas
    re-meshed as saved first)."""
    model, path = saved
    loaded = AtlasReconstructor.load(path)
    probe = model.atlas_._probe
    np.testing.assert_array_equal(loaded._probe.exterior, probe.exterior)
    np.testing.assert_array_equal(loaded._probe.origin, probe.origin)
    assert (loaded._probe.voxel, loaded._probe.step) == (probe.voxel, probe.step)
    at_once = loaded.remesh(lam=6.0)  # two charts meshed, four samples moved
    shown_first = AtlasReconstructor.load(path)
    same_mesh(shown_first.remesh(), model.mesh_)
    same_mesh(at_once, shown_first.remesh(lam=6.0))


def test_a_loaded_atlas_needs_no_torch(saved, tmp_path):
    model, path = saved
    out = tmp_path / "again.ply"
    code = (
        "import sys\n"
        "from reconstruct.pipeline import SurfaceReconstructor\n"
        f"mesh = SurfaceReconstructor.load({str(path)!r}).remesh()\n"
        f"mesh.export({str(out)!r})\n"
        "print('torch' in sys.modules)"  # never imported (a None entry would break scipy)
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "False"
    again = trimesh.load(out, process=False)
    np.testing.assert_allclose(again.vertices, model.mesh_.vertices, atol=1e-5)  # PLY floats
    np.testing.assert_array_equal(again.faces, model.mesh_.faces)


def test_the_remesh_command_takes_a_saved_atlas(saved, tmp_path):
    _, path = saved
    out = tmp_path / "remeshed.stl"
    assert main(["--quiet", "remesh", str(path), "-o", str(out), "--lam", "3"]) == 0
    assert trimesh.load(out, force="mesh").is_watertight
    alone = saved[0].atlas_.save(tmp_path / "alone.npz")  # `AtlasReconstructor.save`'s too
    assert main(["--quiet", "remesh", str(alone), "-o", str(out), "--lam", "3"]) == 0
    assert trimesh.load(out, force="mesh").is_watertight


def damaged_copies(path, tmp_path):
    data = path.read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    flipped = tmp_path / "flipped.npz"  # one byte changed inside the compressed arrays
    middle = bytearray(data)
    middle[len(data) // 2] ^= 0xFF
    flipped.write_bytes(bytes(middle))
    missing = tmp_path / "missing.npz"  # a well-formed archive without one chart's map
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(missing, "w") as target:
        for item in source.infolist():
            if item.filename != "chart1_onnx.npy":
                target.writestr(item, source.read(item.filename))
    flat_probe = tmp_path / "flat_probe.npz"  # well formed, its probe's grid a flat array
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(flat_probe, "w") as target:
        for item in source.infolist():
            if item.filename == "probe_exterior.npy":
                flat = io.BytesIO()
                np.save(flat, np.zeros(8, bool))
                target.writestr(item, flat.getvalue())
            else:
                target.writestr(item, source.read(item.filename))
    nan_point = tmp_path / "nan_point.npz"  # well formed, a point NaN (a hand edit)
    _rewritten(path, nan_point, "points.npy", lambda a: np.where(np.arange(len(a))[:, None] == 3,
                                                                 np.nan, a))
    wide = tmp_path / "wide_embedding.npz"  # well formed, a chart's embedding 5 wide
    _rewritten(path, wide, "chart0_embedding.npy", lambda a: np.tile(a, (1, 3))[:, :5])
    return {"truncated": truncated, "flipped": flipped, "missing": missing,
            "flat_probe": flat_probe, "nan_point": nan_point, "wide_embedding": wide}


def _rewritten(path, target, name, change):
    """A copy of the archive ``path`` at ``target`` with its array ``name`` changed."""
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(target, "w") as copy:
        for item in source.infolist():
            data = source.read(item.filename)
            if item.filename == name:
                array = change(np.load(io.BytesIO(data)))
                data = io.BytesIO()
                np.save(data, array)
                data = data.getvalue()
            copy.writestr(item, data)


@pytest.mark.parametrize("damage", ["truncated", "flipped", "missing", "flat_probe", "nan_point",
                                    "wide_embedding"])
def test_a_damaged_atlas_file_is_one_line_error(saved, tmp_path, capsys, damage):
    _, path = saved
    bad = damaged_copies(path, tmp_path)[damage]
    for load in (SurfaceReconstructor.load, AtlasReconstructor.load):
        with pytest.raises(InvalidInputError) as error:
            load(bad)
        message = str(error.value)
        assert "\n" not in message and message.startswith(str(bad))
        assert "not a ScanStation reconstruction state" in message or "damaged" in message
    out = tmp_path / "never.ply"
    assert main(["--quiet", "remesh", str(bad), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "scanstation: error:" in err and not out.exists()


def test_a_one_chart_state_is_not_an_atlas(tmp_path):
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (400, 2)), rng.normal(0, 0.01, 400)]
    path = SurfaceReconstructor(max_layers=1, max_neurons=6, atlas="never").fit(plane).save(
        tmp_path / "plane.npz")
    with pytest.raises(InvalidInputError, match="not an atlas state"):
        AtlasReconstructor.load(path)
    assert not hasattr(SurfaceReconstructor.load(path), "atlas_")


def test_reconstruct_saves_an_atlas_that_remesh_reads(tmp_path):
    cloud, out, state = tmp_path / "sphere.xyz", tmp_path / "mesh.ply", tmp_path / "state.npz"
    np.savetxt(cloud, sphere_cloud())
    assert main(["--quiet", "reconstruct", str(cloud), "-o", str(out), "--save", str(state)]) == 0
    assert hasattr(SurfaceReconstructor.load(state), "atlas_")
    again = tmp_path / "again.ply"
    assert main(["--quiet", "remesh", str(state), "-o", str(again), "--depth", "3"]) == 0
    assert trimesh.load(out, force="mesh").is_watertight
    assert trimesh.load(again, force="mesh").is_watertight


def test_reconstruct_takes_the_atlas_join_options(tmp_path):
    cloud, out, state = tmp_path / "sphere.xyz", tmp_path / "mesh.ply", tmp_path / "state.npz"
    np.savetxt(cloud, sphere_cloud())
    args = ["--quiet", "reconstruct", str(cloud), "-o", str(out), "--save", str(state)]
    assert main([*args, "--closed", "no", "--voxel", "0.6"]) == 0
    loaded = SurfaceReconstructor.load(state)  # the atlas keeps them; its owner's are for fits
    assert (loaded.atlas_.closed, loaded.atlas_.voxel, loaded.atlas_.closed_) == (False, 0.6, False)
    meta, _ = read_state(state)  # fit-only parameters are not saved: older builds read the state
    assert not {"closed", "voxel"} & {k for part in [meta["reconstructor"], *meta["charts"]]
                                      for k in part["params"]}


@pytest.mark.parametrize(("option", "value"), [("--voxel", "0"), ("--voxel", "nan"),
                                               ("--closed", "maybe")])
def test_bad_atlas_join_options_are_refused(tmp_path, capsys, option, value):
    with pytest.raises(SystemExit):
        main(["reconstruct", str(tmp_path / "c.xyz"), "-o", str(tmp_path / "m.ply"), option,
              value])
    assert option in capsys.readouterr().err


@pytest.mark.parametrize(("params", "message"), [
    ({"closed": "yes"}, "closed must be"), ({"closed": 0}, "closed must be"),
    ({"voxel": 0.0}, "voxel must be"), ({"voxel": True}, "voxel must be"),
    ({"voxel": 1e-300}, "voxel must be a number >= 0.1")])
def test_bad_atlas_join_params_are_refused(params, message):
    with pytest.raises(InvalidInputError, match=message):
        SurfaceReconstructor(**params).fit(sphere_cloud())
    if "voxel" in params:  # the atlas itself, before its charts' fit
        with pytest.raises(InvalidInputError, match=message):
            AtlasReconstructor(**params).fit(sphere_cloud())


def test_the_layered_charts_are_found_from_the_fields_residuals():
    atlas = AtlasReconstructor(random_state=0).fit(sphere_cloud())
    for chart, members, detail in zip(atlas.charts_, atlas.chart_points_, atlas.details_,
                                      strict=True):
        assert sampled_kurtosis(detail.residuals_) == residual_kurtosis(
            chart.mesh_, atlas.points_[np.asarray(members)])
    found = atlas._layered_charts()
    del atlas.details_  # (a state saved before the fields: from the meshes again)
    np.testing.assert_array_equal(found, atlas._layered_charts())
