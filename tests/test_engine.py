"""The incremental engine: merged cloud, updates as views stream in, warm starts, determinism,
re-meshing without retraining, and its saved state."""

import dataclasses
import os
import time
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from daemon_helpers import wait_until
from surface_checks import hits_per_ray, side_rays

from capture.live.atlas_fit import atlas_reason
from capture.live.cloud import VoxelCloud
from capture.live.engine import EngineError, IncrementalEngine, remesh
from capture.live.patch_fit import fit_fresh, fit_warm
from capture.plan import PlanError
from reconstruct.alignment import align_embedding
from reconstruct.metrics import distance_to_surface, sample_surface


def capped_cylinder() -> trimesh.Trimesh:
    """A 40 mm radius, 100 mm tall surface of revolution with a domed top, open at the bottom."""
    z = np.linspace(0, 100, 26)
    t = np.linspace(0, np.pi / 2, 10)[1:]
    profile = np.r_[np.c_[np.full(len(z), 40.0), z], np.c_[40 * np.cos(t), 100 + 20 * np.sin(t)]]
    return trimesh.creation.revolve(profile, sections=64)


def views(mesh, n_views=12, seed=0):
    """What a camera at azimuth -90° - θ sees for each table angle θ: the points facing it,
    rotated into the object frame, with 0.3 mm noise; one (m, 3) array per view."""
    points, faces = trimesh.sample.sample_surface_even(mesh, 6000, seed=seed)
    normals = mesh.face_normals[faces]
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_views):
        a = np.radians(-90.0 - 360.0 * k / n_views)
        to_camera = np.array([np.cos(a), np.sin(a), 0.5])
        seen = normals @ to_camera > 0.2
        out.append(points[seen] + rng.normal(0, 0.3, (seen.sum(), 3)))
    return out


@pytest.fixture(scope="module")
def stream():
    return capped_cylinder(), views(capped_cylinder())


def run_engine(stream_views, params, **kwargs):
    figures = []
    engine = IncrementalEngine(params, on_mesh=lambda e, f: figures.append(f), **kwargs)
    try:
        for points in stream_views:
            engine.add_view(points)
        engine.finish(timeout=120)
    finally:
        engine.close()
    return engine, figures


def test_voxel_cloud_averages_and_counts_views():
    cloud = VoxelCloud(2.0)
    assert cloud.add([[0.5, 0.5, 0.5], [5.0, 5.0, 5.0]]) == 2
    assert cloud.add([[1.5, 1.5, 1.5]]) == 0  # same voxel as the first point
    np.testing.assert_allclose(cloud.points(), [[1, 1, 1], [5, 5, 5]])
    np.testing.assert_allclose(cloud.points(min_views=2), [[1, 1, 1]])
    other = VoxelCloud(2.0)
    other.add([[1.5, 1.5, 1.5]])
    other.add([[0.5, 0.5, 0.5], [5.0, 5.0, 5.0]])
    np.testing.assert_allclose(other.points(), cloud.points())
    with pytest.raises(ValueError, match="voxel_mm must be > 0"):
        VoxelCloud(0)


def _flat_face(z: float, n: int = 30000, seed: int = 0) -> np.ndarray:
    """(n, 3) points of a 50 mm square face at height ``z`` mm, σ 0.1 mm."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 50, (n, 2)), z + rng.normal(0, 0.1, n)])


def test_a_face_on_a_voxel_boundary_is_one_layer_of_points():
    on_boundary = VoxelCloud(2.0)  # the vase's top: z = 120 mm = 60 voxels
    on_boundary.add(_flat_face(120.0))
    assert len(on_boundary) > 1200  # two layers of voxels, 25 x 25 each
    points = on_boundary.points()
    assert len(points) < 1.05 * 625  # about one point per column of voxels (24 points a voxel:
    assert np.median(np.abs(points[:, 2] - 120.0)) < 0.02  # a few means lie 0.25 voxel apart)
    inside = VoxelCloud(2.0)  # a face in mid-voxel: one layer, untouched
    inside.add(_flat_face(121.0))
    assert len(inside) == len(inside.points()) == 625


def test_a_surface_whose_views_a_voxel_face_splits_is_seen_by_both():
    cloud = VoxelCloud(2.0)  # one view on each side of z = 2 mm: seen twice, as one point
    cloud.add([[1.0, 1.0, 1.99]])
    cloud.add([[1.05, 1.0, 2.01]])
    np.testing.assert_allclose(cloud.points(min_views=2), [[1.025, 1.0, 2.0]])


def test_two_sheets_a_voxel_apart_are_not_joined():
    cloud = VoxelCloud(2.0)
    cloud.add(np.vstack([_flat_face(119.4), _flat_face(120.6, seed=1)]))
    points = cloud.points()
    assert len(points) == len(cloud) == 1250
    assert sorted(np.unique(np.round(points[:, 2]))) == [119.0, 121.0]


def test_meshes_grow_with_the_views_and_the_last_one_is_final(stream, fast_params):
    truth, stream_views = stream
    engine, figures = run_engine(stream_views, fast_params, total_views=len(stream_views),
                                 background=False)
    assert [f["version"] for f in figures] == list(range(1, len(figures) + 1))
    assert len(figures) >= 2 and figures[-1]["final"] and not figures[0]["final"]
    assert figures[0]["views"] < figures[-1]["views"] == 12
    assert [f["views"] for f in figures].count(12) == 1  # no extra update on the last view
    assert figures[-1]["patches"] == 4 and figures[-1]["patches_waiting"] == 0
    assert figures[-1]["patches_fresh"] + figures[-1]["patches_warm"] >= 1
    assert sum(f["patches_warm"] for f in figures) >= 1  # later fits start from earlier nets
    assert sum(f["patches_fresh"] for f in figures) >= 1  # the search ran …
    assert sum(f["patches_fixed"] for f in figures) >= 1  # … and its architecture was reused
    assert {m.hidden_layers_ for m in (f.model for f in engine.cache.fits.values())} == {
        engine.cache.layers}
    samples = sample_surface(engine.mesh, 4000)
    assert np.median(distance_to_surface(truth, samples)) < 1.0
    assert np.quantile(distance_to_surface(engine.mesh, sample_surface(truth, 4000)), 0.9) < 2.0
    # the patches, fitted by the paper's pipeline, merge into one layer: no doubled seams
    angles = np.r_[np.arange(0.5, 360, 2.0), np.arange(0, 360, 120) - 0.1]  # + seam planes
    hits = hits_per_ray(engine.mesh, *side_rays(np.linspace(10, 90, 5), angles))
    assert np.mean(hits == 1) > 0.99 and hits.max() == 1, np.bincount(hits)


def test_same_views_and_schedule_same_mesh_whatever_the_threads(stream, fast_params):
    """A live engine skips updates it could not keep up with; its schedule, replayed inline
    (as `scanstation replay` does from the recording), gives the same mesh."""
    _, stream_views = stream
    background, figures = run_engine(stream_views, fast_params)
    assert figures[-1]["schedule"] == background.schedule_run
    assert set(background.schedule_run) <= {3, 6, 9}
    inline, _ = run_engine(stream_views, fast_params, background=False,
                           schedule=background.schedule_run)
    assert inline.schedule_run == background.schedule_run
    np.testing.assert_array_equal(background.mesh.vertices, inline.mesh.vertices)
    np.testing.assert_array_equal(background.mesh.faces, inline.mesh.faces)
    every, _ = run_engine(stream_views, fast_params, background=False)
    assert every.schedule_run == [3, 6, 9, 12]  # inline never lags, so it skips none


def test_remesh_without_training_survives_a_reload(stream, tmp_path, fast_params):
    _, stream_views = stream
    engine, figures = run_engine(stream_views[:6], fast_params)
    counts, before, last = dict(engine.cache.counts), engine.mesh, engine.version
    version = remesh(engine, lam=4.0)
    assert version == last + 1 and figures[-1]["refined"] and figures[-1]["lam"] == 4.0
    assert engine.cache.counts == counts  # nothing was fitted again
    assert len(engine.mesh.faces) > 0 and not np.array_equal(engine.mesh.vertices,
                                                              before.vertices)
    engine.save(tmp_path)
    path = remesh(tmp_path, lam=4.0)
    assert path.name == "mesh-lam4-depth2.ply"
    again = trimesh.load(path, process=False)
    np.testing.assert_allclose(again.vertices, engine.mesh.vertices, atol=1e-5)
    with pytest.raises(EngineError, match="no saved reconstruction"):
        remesh(tmp_path / "nothing")


def test_an_abandoned_engine_ends_its_worker_processes(fast_params):
    """close(wait=False) (a cancelled scan) ends the fits under way with their processes: the
    program's exit waited for them (Ctrl-C on the main job: 3.0-4.6 s, now about 1 s)."""
    engine = IncrementalEngine(fast_params, workers=2)
    fits = [engine._executor.submit(time.sleep, 60) for _ in range(2)]  # two fits under way
    wait_until(lambda: all(f.running() for f in fits), 60, what="the fits to start")
    workers = list(engine._executor._processes)
    engine.close(wait=False)

    def gone(pid):
        try:
            os.waitpid(pid, os.WNOHANG)
            os.kill(pid, 0)
        except (ChildProcessError, ProcessLookupError):
            return True
        return False

    wait_until(lambda: all(gone(pid) for pid in workers), 30, what="the workers to end")


def test_remesh_before_any_mesh_is_an_error(fast_params):
    engine = IncrementalEngine(fast_params, background=False)
    with pytest.raises(EngineError, match="nothing to re-mesh"):
        engine.remesh(lam=2.0)


def test_alignment_recovers_a_rotation_with_reflection():
    rng = np.random.default_rng(1)
    uv = rng.normal(size=(50, 2))
    turn = np.array([[0.0, 1.0], [1.0, 0.0]]) @ np.array([[0.6, -0.8], [0.8, 0.6]])
    apply, residual = align_embedding(uv @ turn + [3.0, -2.0], uv)
    assert residual < 1e-9
    np.testing.assert_allclose(apply(uv @ turn + [3.0, -2.0]), uv, atol=1e-9)


def test_warm_start_fine_tunes_the_same_network_and_refuses_strangers(stream, fast_params):
    truth, stream_views = stream
    patch = np.concatenate(stream_views[:3])
    patch = patch[(patch[:, 1] < -5) & (patch[:, 2] < 95)]
    first = fit_fresh(patch[: len(patch) // 2], fast_params)
    warm = fit_warm(patch, first, fast_params, tolerance=1.0)
    assert warm is not None and warm.hidden_layers_ == first.hidden_layers_
    assert warm.mlp_.history_[-1].get("fine_tune")
    far = patch + [0.0, 0.0, 500.0]  # no point in common with the first fit
    assert fit_warm(far, first, fast_params, tolerance=1.0) is None


def cup() -> trimesh.Trimesh:
    """An open 40 mm radius, 60 mm tall cup with a 10 mm wall (its inside: not star-shaped)."""
    profile = np.array([(40, 0), (40, 60), (30, 60), (30, 8), (0, 8)], dtype=float)
    return trimesh.creation.revolve(profile, sections=64)


@pytest.fixture(scope="module")
def cup_engine(fast_params):
    """The cup's 12 views through an engine whose plan asks for the atlas (live, its thread)."""
    params = dataclasses.replace(fast_params, surface="atlas")
    engine, figures = run_engine(views(cup()), params, total_views=12)
    return engine, figures, params


def test_the_final_mesh_of_a_cup_is_an_atlas_with_both_walls(cup_engine):
    engine, figures, _ = cup_engine
    assert [f["surface"] for f in figures[:-1]] == ["sectors"] * (len(figures) - 1)  # previews
    final = figures[-1]
    assert final["final"] and final["surface"] == "atlas" == engine.surface
    assert final["charts"] == len(engine.atlas.charts_) >= 2
    assert final["atlas_reason"] == "the plan asks for an atlas"
    assert engine.mesh is engine.atlas.mesh_
    assert not engine.atlas.closed_  # a scan's atlas is joined open (nothing sees under it)
    truth = cup()
    assert np.quantile(distance_to_surface(truth, sample_surface(engine.mesh, 4000)), 0.9) < 2.0
    inside = sample_surface(truth, 4000)
    inside = inside[np.hypot(inside[:, 0], inside[:, 1]) < 31]  # the inner wall and floor
    assert np.quantile(distance_to_surface(engine.mesh, inside), 0.8) < 2.0
    # a ray from the axis halfway up meets the inner wall, then the outer one
    hits = hits_per_ray(engine.mesh, *side_rays([30.0], np.arange(5, 360, 30.0)))
    assert np.median(hits) == 2, hits
    # it faces the camera: its outer wall out, whatever sign its charts' normals took
    centre, normal = engine.mesh.triangles_center, engine.mesh.face_normals
    outer = (np.hypot(centre[:, 0], centre[:, 1]) > 37) & (centre[:, 2] > 10)
    radial = np.einsum("ij,ij->i", normal[outer, :2], centre[outer, :2])
    assert np.sum(engine.mesh.area_faces[outer] * (radial > 0)) > 0.9 * np.sum(
        engine.mesh.area_faces[outer])


def test_a_replayed_atlas_scan_gives_the_same_mesh(cup_engine):
    live, figures, params = cup_engine
    inline, _ = run_engine(views(cup()), params, background=False, total_views=12,
                           schedule=figures[-1]["schedule"])
    assert inline.surface == "atlas"
    np.testing.assert_array_equal(inline.mesh.vertices, live.mesh.vertices)
    np.testing.assert_array_equal(inline.mesh.faces, live.mesh.faces)


def test_an_atlas_remeshes_without_training_and_survives_a_reload(cup_engine, tmp_path):
    engine, _, _ = cup_engine
    counts, before = dict(engine.cache.counts), engine.mesh
    engine.remesh(lam=4.0)
    assert engine.figures["surface"] == "atlas" and engine.figures["refined"]
    assert engine.cache.counts == counts  # nothing was fitted again
    assert engine.mesh is engine.atlas.mesh_ and engine.mesh is not before
    engine.save(tmp_path)
    assert (tmp_path / "engine" / "atlas.npz").is_file()
    assert not list((tmp_path / "engine").glob("patch-*.npz"))  # the atlas is the state
    path = remesh(tmp_path, lam=4.0)
    again = trimesh.load(path, process=False)
    np.testing.assert_allclose(again.vertices, engine.mesh.vertices, atol=1e-5)
    loaded = IncrementalEngine.load(tmp_path)
    assert loaded.surface == "atlas" and len(loaded.atlas.charts_) == len(engine.atlas.charts_)


def _fit(unexplained, folded=False):
    """A stand-in patch fit: its unexplained share and a flat or folded two-triangle mesh."""
    corner = [1, 0, 0.05] if folded else [-1, 0, 0.0]  # back onto the first face, or beside it
    mesh = trimesh.Trimesh([[0, 0, 0], [0, 1, 0], [1, 0, 0], corner], [[0, 1, 2], [0, 3, 1]],
                           process=False)
    return SimpleNamespace(unexplained_=unexplained, mesh_=mesh)


def test_auto_takes_the_atlas_only_when_a_sector_is_unfaithful(fast_params):
    auto = dataclasses.replace(fast_params, surface="auto")
    good = {"sector 0": _fit(0.0), "sector 1": _fit(0.009)}
    assert atlas_reason(auto, good, final=True) is None
    unexplained = {**good, "sector 2": _fit(0.032)}  # the figurine's worst sector
    reason = atlas_reason(auto, unexplained, final=True)
    assert reason == "sector 2 leaves 3 % of its points unexplained: not one disc-like surface"
    assert "folds over" in atlas_reason(auto, {**good, "cap": _fit(0.0, folded=True)}, True)
    assert atlas_reason(auto, unexplained, final=False) is None  # previews stay sectors
    sectors = dataclasses.replace(fast_params, surface="sectors")
    assert atlas_reason(sectors, unexplained, final=True) is None
    always = dataclasses.replace(fast_params, surface="atlas")
    assert atlas_reason(always, good, final=True) == "the plan asks for an atlas"
    with pytest.raises(PlanError, match="reconstruction.surface must be one of"):
        dataclasses.replace(fast_params, surface="cylinders").validate()
