"""A fitted `AtlasReconstructor` written to a folder and read back, ready to `remesh` (no
training, no pickle): every chart's `SurfaceReconstructor.save` state, and what the join needs
(the points, each point's chart, the charts' orientations, the spacing, the parameters).

Until the atlas has its own ``save`` / ``load``, the scan engine keeps its final atlas with
these (`capture.live.engine`). A loaded atlas re-meshes and joins exactly as the fitted one.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from .atlas import AtlasReconstructor
from .charts import ChartDecomposition
from .errors import InvalidInputError, NotFittedError
from .io import write_bytes_atomic
from .pipeline import SurfaceReconstructor

ATLAS_FORMAT = "scanstation-atlas/1"
_JOIN = "join.npz"


def save_atlas(atlas: AtlasReconstructor, directory) -> Path:
    """Write a fitted ``atlas`` into ``directory`` (created): ``chart-i.npz`` and ``join.npz``."""
    if not hasattr(atlas, "charts_"):
        raise NotFittedError("nothing to save: fit() the atlas first")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for i, chart in enumerate(atlas.charts_):
        chart.save(directory / f"chart-{i}.npz")
    # Each point's chart among the fitted ones (−1: none), as the join counts them.
    ids = np.asarray(atlas._chart_ids)
    labels = atlas.decomposition_.labels_
    position = np.searchsorted(ids, labels)
    found = (labels >= 0) & (position < len(ids)) & (ids[np.minimum(position, len(ids) - 1)]
                                                     == labels)
    labels = np.where(found, position, -1)
    meta = {"format": ATLAS_FORMAT, "params": _params(atlas), "charts": len(atlas.charts_),
            "spacing": float(atlas.decomposition_.spacing_)}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
                        points=atlas.points_, labels=labels, signs=np.asarray(atlas.signs_),
                        mesh_vertices=atlas.mesh_.vertices, mesh_faces=atlas.mesh_.faces)
    write_bytes_atomic(directory / _JOIN, buffer.getvalue())
    return directory


def load_atlas(directory) -> AtlasReconstructor:
    """An `AtlasReconstructor` read from ``directory`` (written by `save_atlas`): ``mesh_`` as
    saved, ``charts_`` loaded; `remesh` works at once."""
    import trimesh

    directory = Path(directory)
    try:
        with np.load(directory / _JOIN, allow_pickle=False) as data:
            meta = json.loads(bytes(data["meta"]).decode())
            points, labels, signs = data["points"], data["labels"], data["signs"]
            mesh = trimesh.Trimesh(data["mesh_vertices"], data["mesh_faces"], process=False)
    except Exception as exc:
        raise InvalidInputError(f"{directory}: not a saved atlas ({exc})") from exc
    if meta.get("format") != ATLAS_FORMAT:
        raise InvalidInputError(f"{directory}: unsupported atlas format {meta.get('format')!r}")
    atlas = AtlasReconstructor(**meta["params"])
    atlas.charts_ = [SurfaceReconstructor.load(directory / f"chart-{i}.npz")
                     for i in range(int(meta["charts"]))]
    for chart in atlas.charts_:
        chart.remesh()  # its mesh: what the join samples
    decomposition = ChartDecomposition(random_state=atlas.random_state)
    decomposition.labels_ = labels
    decomposition.spacing_ = float(meta["spacing"])
    atlas.decomposition_ = decomposition
    atlas._chart_ids = list(range(len(atlas.charts_)))
    atlas.chart_points_ = [np.flatnonzero(labels == i) for i in range(len(atlas.charts_))]
    atlas.points_ = points
    atlas.signs_ = signs
    atlas.mesh_ = mesh
    atlas.faults_ = []
    atlas.timings_ = {}
    return atlas


def _params(atlas: AtlasReconstructor) -> dict:
    params = atlas.get_params(deep=False)
    if params.get("graph") is not None:
        raise InvalidInputError("cannot save an atlas fitted with its own SheetGraph")
    params.pop("graph", None)
    return params
