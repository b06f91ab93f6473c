"""A one-chart reconstruction's fitted state as (meta, arrays), and the reconstruction back
from it (`SurfaceReconstructor.state`, `from_state`): its parameters, the embedded points, the
ONNX map and the boundary samples of every depth used — what re-meshing needs, and no network.
An atlas saves one such state per chart (`reconstruct.atlas_state`)."""

from __future__ import annotations

import numpy as np

from .surface_map import OnnxSurfaceMap

STATE_FORMAT = "scanstation-reconstruction/1"


def reconstruction_state(reconstructor, params: dict,
                         prefix: str = "") -> tuple[dict, dict[str, np.ndarray]]:
    """(meta, arrays named ``prefix`` + embedding (m, 2) / points (m, 3) / onnx (bytes) /
    boundary_<boundary>_<depth>_<corners> (k, 2)) of a fitted one-chart ``reconstructor``
    with its saved ``params``."""
    meta = {
        "format": STATE_FORMAT,
        "params": params,
        "embedding_method": reconstructor.embedding_method_,
        "n_neighbors": int(reconstructor.n_neighbors_),
        "hidden_layers": list(reconstructor.hidden_layers_),
    }
    arrays = {f"{prefix}embedding": reconstructor.embedding_,
              f"{prefix}points": reconstructor.points_,
              f"{prefix}onnx": np.frombuffer(reconstructor.surface_map_.to_bytes(),
                                             dtype=np.uint8)}
    for key, points in getattr(reconstructor, "_boundary_cache", {}).items():
        if isinstance(key, tuple):  # the boundary samples of each (boundary, depth,
            # n_corners) used; not the KD-tree or the geometry (rebuilt when needed)
            arrays[f"{prefix}boundary_{key[0]}_{key[1]}_{key[2]}"] = points
    return meta, arrays


def reconstruction_from_state(cls, meta: dict, arrays: dict, prefix: str = ""):
    """A ``cls`` (`SurfaceReconstructor`) rebuilt from `reconstruction_state`'s (meta,
    arrays): it can `remesh()` at once."""
    self = cls(**meta["params"])
    self.embedding_ = np.asarray(arrays[f"{prefix}embedding"], float)
    self.points_ = np.asarray(arrays[f"{prefix}points"], float)
    m = len(self.embedding_)
    if (self.embedding_.shape != (m, 2) or self.points_.shape != (m, 3)
            or not (np.isfinite(self.embedding_).all() and np.isfinite(self.points_).all())):
        raise ValueError(f"its embedding {self.embedding_.shape} and points "
                         f"{self.points_.shape} do not agree, or a value is not finite")
    self.embedding_method_ = meta["embedding_method"]
    self.n_neighbors_ = int(meta["n_neighbors"])
    self.hidden_layers_ = tuple(meta["hidden_layers"])
    self.surface_map_ = OnnxSurfaceMap.from_bytes(bytes(arrays[f"{prefix}onnx"]))
    self._boundary_cache = {}
    for name in arrays:
        if name.startswith(f"{prefix}boundary_"):
            boundary, depth, n_corners = name[len(f"{prefix}boundary_"):].split("_")
            self._boundary_cache[(boundary, int(depth), int(n_corners))] = np.asarray(
                arrays[name], float)
    return self
