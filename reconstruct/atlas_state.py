"""An atlas's fitted state as (meta, arrays), and the atlas back from it
(`AtlasReconstructor.state`, `from_state`): every chart's `SurfaceReconstructor.state`, the
cloud and its partition, the charts' orientation and sides, the join's last samples and mesh,
and each chart's part of the join: what re-meshing needs, and no network."""

from __future__ import annotations

import numpy as np

from .chart_parts import parts_from_state, parts_state
from .charts import ChartDecomposition
from .closed_grid import ClosedSDF
from .errors import NotFittedError
from .join import ExteriorProbe
from .residual_detail import ResidualDetail
from .sdf_grid import SparseSDF

ATLAS_FORMAT = "scanstation-atlas/1"
#: Parameters of the fit alone, not saved: a loaded atlas re-meshes, it does not fit.
FIT_ONLY_PARAMS = ("graph", "n_jobs", "hidden_layers", "n_neighbors", "max_layers",
                   "max_neurons")


def atlas_state(atlas) -> tuple[dict, dict[str, np.ndarray]]:
    """The fitted state as (meta, arrays): every chart's `SurfaceReconstructor.state`
    (embedded points, ONNX map, parameters, boundary samples; arrays ``chart<i>_*``), the
    cloud ``points`` (n, 3), its partition ``labels`` (n,), the ``chart_points`` of each
    chart (flat, cut at ``chart_offsets``) and the ``signs`` (c,) — what re-joining needs,
    and no network — the join's last samples and mesh (`SparseSDF.state` with its grid,
    so a loaded open atlas re-meshes incrementally too; `ClosedSDF.state` without: a closed
    one's first re-mesh that moves a sample evaluates its grid afresh), ``join_*``, and
    each chart's part of the join (`chart_parts.parts_state`, ``part<i>_*``: a loaded atlas's
    first re-mesh skips the charts whose part cannot change, as the atlas saved would), and
    a closed join's `join.ExteriorProbe` (``probe_*``: it turns the charts' folded flaps as
    the atlas saved does; built again from the samples it was saved with, it was another
    probe, and a direct re-mesh gave another mesh: hook 22k, 1,176 of 36,432 vertices)."""
    if not hasattr(atlas, "charts_"):
        raise NotFittedError("nothing to save: fit() the atlas first")
    charts, arrays = [], {}
    for index, chart in enumerate(atlas.charts_):
        meta, chart_arrays = chart.state(prefix=f"chart{index}_")
        charts.append(meta)
        arrays.update(chart_arrays)
    meta = {
        "format": ATLAS_FORMAT,
        "params": {k: v for k, v in atlas.get_params(deep=False).items()
                   if k not in FIT_ONLY_PARAMS},
        "charts": charts,
        "chart_ids": [int(i) for i in atlas._chart_ids],
        "spacing": float(atlas.decomposition_.spacing_),
        "faults": list(atlas.faults_),
        "closed": bool(atlas.closed_),
        "seal": float(atlas.seal_),
    }
    if atlas.__dict__.get("noise_") is not None:
        meta["noise"] = float(atlas.noise_)
    if hasattr(atlas, "_sdf") and hasattr(atlas._sdf, "samples_"):
        meta["join"], join_arrays = atlas._sdf.state(prefix="join_")
        arrays.update(join_arrays)
    sizes = [len(members) for members in atlas.chart_points_]
    arrays.update(points=atlas.points_, labels=atlas.decomposition_.labels_,
                  chart_points=np.concatenate(atlas.chart_points_),
                  chart_offsets=np.cumsum([0, *sizes]), signs=np.asarray(atlas.signs_),
                  shells=np.asarray(atlas.shells_, bool),
                  thin=np.asarray(atlas.thin_, bool))
    details = atlas.__dict__.get("details_")
    if details is not None:  # each chart's residuals, in chart_points' order
        meta["detail"] = {"width": details[0].width if details else 0.0,
                          "variance": [d.variance_ for d in details],
                          "shape": [d.shape_ for d in details]}
        arrays["detail_residuals"] = np.concatenate([np.zeros(0), *(d.residuals_
                                                                    for d in details)])
    parts = atlas.__dict__.get("_parts")
    if parts is not None and len(parts) == len(atlas.charts_):
        arrays.update(parts_state(parts))
    probe = atlas.__dict__.get("_probe")
    if atlas.closed_ and isinstance(probe, ExteriorProbe):  # it turns a closed join's flaps
        # (an open join never asks it: not saved)
        meta["probe"] = {"voxel": probe.voxel, "step": probe.step}
        arrays.update(probe_origin=probe.origin, probe_exterior=probe.exterior)
    return meta, arrays


def atlas_from_state(cls, meta: dict, arrays: dict):
    """Rebuild a fitted atlas from `state`; it can `remesh()` at once (no torch needed).
    Its ``decomposition_`` holds ``labels_`` and ``spacing_`` only; ``mesh_`` comes with
    the first `remesh`. ``cls``: `AtlasReconstructor`."""
    from .pipeline import SurfaceReconstructor

    atlas = cls(**meta["params"])
    atlas.charts_ = [SurfaceReconstructor.from_state(chart, arrays, prefix=f"chart{i}_")
                     for i, chart in enumerate(meta["charts"])]
    for chart in atlas.charts_:  # a chart keeps the side its map gives (signs_ turn it),
        chart.up = None  # also when saved before charts had the parameter
    atlas.points_ = np.asarray(arrays["points"], float)
    labels = np.asarray(arrays["labels"], np.int64)
    offsets = np.asarray(arrays["chart_offsets"], np.int64)
    flat = np.asarray(arrays["chart_points"], np.int64)
    atlas.chart_points_ = [flat[a:b] for a, b in zip(offsets[:-1], offsets[1:], strict=True)]
    atlas.signs_ = np.asarray(arrays["signs"], float)
    atlas._chart_ids = [int(i) for i in meta["chart_ids"]]
    n_charts = len(atlas.charts_)
    if not (len(atlas.signs_) == len(atlas.chart_points_) == len(atlas._chart_ids) == n_charts
            == len(arrays["shells"])
            and labels.shape == (len(atlas.points_),) and atlas.points_.ndim == 2
            and atlas.points_.shape[1:] == (3,) and np.isfinite(atlas.points_).all()
            and (len(flat) == 0 or 0 <= flat.min() and flat.max() < len(atlas.points_))):
        raise ValueError("its charts, signs and points do not agree, or a point is not finite")
    atlas.decomposition_ = ChartDecomposition(chart_size=atlas.chart_size,
                                              overlap=atlas.overlap)
    atlas.decomposition_.labels_ = labels
    atlas.decomposition_.spacing_ = float(meta["spacing"])
    atlas.faults_ = [str(fault) for fault in meta["faults"]]
    atlas.closed_, atlas.seal_ = bool(meta["closed"]), float(meta["seal"])
    if meta.get("noise") is not None:  # (states saved before it was measured have none)
        atlas.noise_ = float(meta["noise"])
    if "detail" in meta:  # (states saved before it was built join the charts as they are)
        atlas.details_ = _details(meta["detail"], arrays["detail_residuals"], atlas.points_,
                                  atlas.chart_points_, offsets)
    atlas.shells_ = np.asarray(arrays["shells"], bool)
    # states written before thin parts were told apart have none
    atlas.thin_ = (np.asarray(arrays["thin"], bool) if "thin" in arrays
                   else np.zeros(n_charts, bool))
    if atlas.thin_.shape != atlas.shells_.shape:
        raise ValueError("its thin parts and shells do not agree")
    atlas.timings_ = {}
    if "probe" in meta:  # (states saved before it was kept build it again from their samples)
        atlas._probe = ExteriorProbe.restored(arrays["probe_origin"], arrays["probe_exterior"],
                                              **meta["probe"])
    if "join" in meta:  # the join's grid and last mesh: the first re-mesh is incremental
        kind = ClosedSDF if meta["join"].get("kind") == "closed" else SparseSDF
        atlas._sdf = kind.from_state(meta["join"], arrays, prefix="join_")
        parts = parts_from_state(arrays, n_charts)  # with them, it skips charts at once
        if parts is not None:
            atlas._parts = parts
    return atlas


def _details(meta: dict, residuals, points, chart_points, offsets) -> list[ResidualDetail]:
    """Each chart's `ResidualDetail` from a state's ``detail`` meta and residuals (flat, cut
    at ``offsets`` as the charts' points)."""
    residuals = np.asarray(residuals, float)
    if not (len(residuals) == offsets[-1] and len(meta["variance"]) == len(meta["shape"])
            == len(chart_points)):
        raise ValueError("its charts' residuals and points do not agree")
    return [ResidualDetail(float(meta["width"])).set_fitted(
                points[members], residuals[a:b], variance, shape)
            for members, a, b, variance, shape in zip(
                chart_points, offsets[:-1], offsets[1:], meta["variance"], meta["shape"],
                strict=True)]
