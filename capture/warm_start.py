"""Fitting one patch with the paper's pipeline, from scratch or warm-started from an earlier fit.

A fresh fit is `SurfaceReconstructor`'s: embed (Isomap / MLLE), grow the adaptive MLP, mesh; or,
once a patch of the scan has found an architecture, embed and train that architecture
(`FixedArchitectureMLP`). A warm start reuses a fitted network: the new cloud is embedded, its
embedding is aligned (rotation, reflection, shift: orthogonal Procrustes) to the earlier fit's
embedding on the points both clouds share, and the earlier MLP is fine-tuned on the new samples
(no architecture search). This is for the same patch after more views (measured: warm-starting a
neighbouring patch from its neighbour's network degrades along the chain, so a patch's first fit
is always fresh); when too few points are shared or the embeddings disagree, the fit starts
fresh.
"""

from __future__ import annotations

import copy
import logging

import numpy as np
from scipy.spatial import cKDTree

from reconstruct.embedding import SurfaceEmbedding
from reconstruct.mlp import AdaptiveMLP
from reconstruct.pipeline import SurfaceReconstructor

from .fixed_mlp import FixedArchitectureMLP
from .plan import ReconstructionParams

log = logging.getLogger(__name__)

#: The engine keeps the better of each fit's two final trainings, not their mean: a patch's net
#: is fine-tuned again after more views, and the mean is twice as wide (measured on bench.scan:
#: 54.7 s against 58.3 s, target 60 s).
FINAL_FIT = "better"
#: ... and stops those trainings after 6 flat epochs, the search's patience: bench.scan ran at
#: 59.9 s of its 60 s budget with 6 (the pipeline's 10 was not measured there).
FINAL_PATIENCE = 6

#: A warm start needs this share of the new points matched to the earlier fit's points …
MIN_SHARED = 0.15
#: … and an alignment residual below this share of the earlier embedding's extent.
MAX_ALIGN_ERROR = 0.08


def _assemble(embedding: SurfaceEmbedding, points, mlp: AdaptiveMLP,
              params: ReconstructionParams) -> SurfaceReconstructor:
    """A fitted `SurfaceReconstructor` from its fitted steps, meshed at ``params``' λ, depth."""
    model = SurfaceReconstructor(
        lam=params.lam, depth=params.depth, max_layers=params.max_layers,
        max_neurons=params.max_neurons, random_state=params.seed,
    )
    model.embedding_ = embedding.embedding_
    model.points_ = points[embedding.support_]
    model.embedding_method_ = embedding.method_
    model.n_neighbors_ = embedding.n_neighbors_
    model.mlp_ = mlp
    model.surface_map_ = mlp.surface_map_
    model.hidden_layers_ = tuple(mlp.hidden_layers_)
    model.remesh()
    return model


def fit_fresh(points, params: ReconstructionParams) -> SurfaceReconstructor:
    """The paper's whole pipeline on (n, 3) points with the plan's MLP limits."""
    embedding = SurfaceEmbedding(random_state=params.seed).fit(points)
    mlp = AdaptiveMLP(
        max_layers=params.max_layers, max_neurons=params.max_neurons,
        max_epochs=params.max_epochs, final_epochs=params.final_epochs,
        max_train_points=params.max_train_points, final_fit=FINAL_FIT,
        final_patience=FINAL_PATIENCE, random_state=params.seed,
    ).fit(embedding.embedding_, points[embedding.support_])
    return _assemble(embedding, points, mlp, params)


def fit_fixed(points, layers, params: ReconstructionParams,
              polish: bool = False) -> SurfaceReconstructor:
    """Embed (n, 3) points and train an MLP of hidden ``layers`` (no search); ``polish``: with
    the ``polish_*`` epochs, patience and samples."""
    embedding = SurfaceEmbedding(random_state=params.seed).fit(points)
    if polish:
        training = {"final_epochs": params.polish_epochs, "patience": params.polish_patience,
                    "max_train_points": params.polish_train_points}
    else:
        training = {"final_epochs": params.final_epochs,
                    "max_train_points": params.max_train_points}
    mlp = FixedArchitectureMLP(tuple(layers), final_fit=FINAL_FIT, random_state=params.seed,
                               **training)
    mlp.fit(embedding.embedding_, points[embedding.support_])
    return _assemble(embedding, points, mlp, params)


def shared_points(previous: SurfaceReconstructor, points, tolerance: float):
    """Index pairs (into ``points``, into ``previous.points_``) of points within ``tolerance``."""
    distance, index = cKDTree(previous.points_).query(points, distance_upper_bound=tolerance)
    mine = np.flatnonzero(np.isfinite(distance))
    return mine, index[mine]


def align_embedding(new_uv, old_uv):
    """Orthogonal Procrustes (reflection allowed, no scale) of paired 2D points.

    new_uv, old_uv : (k, 2) the same points in the two embeddings.
    Returns (apply: (n, 2) → (n, 2), RMS residual of the pairs in ``old_uv`` units).
    """
    a_mean, b_mean = new_uv.mean(axis=0), old_uv.mean(axis=0)
    u, _, vt = np.linalg.svd((new_uv - a_mean).T @ (old_uv - b_mean))
    rotation = u @ vt

    def apply(uv):
        return (np.asarray(uv) - a_mean) @ rotation + b_mean

    residual = float(np.sqrt(np.mean(np.sum((apply(new_uv) - old_uv) ** 2, axis=1))))
    return apply, residual


def fit_patch(points, previous, params: ReconstructionParams, polish: bool = False,
              layers=None):
    """(fitted `SurfaceReconstructor`, how) for (n, 3) ``points``: "warm" from ``previous``
    (the same patch's earlier fit) when it can be; else "fixed" at the scan's architecture
    ``layers`` when one is known; else "fresh" (the search). ``polish``: the final fit, trained
    longer on more samples (``polish_*`` parameters)."""
    if previous is not None:
        model = fit_warm(points, previous, params, tolerance=params.voxel_mm, polish=polish)
        if model is not None:
            return model, "warm"
        layers = layers or previous.hidden_layers_
    if layers:
        return fit_fixed(points, layers, params, polish=polish), "fixed"
    model = fit_fresh(points, params)
    if polish:
        model = fit_warm(points, model, params, tolerance=params.voxel_mm, polish=True) or model
    return model, "fresh"


def fit_warm(points, previous: SurfaceReconstructor, params: ReconstructionParams,
             tolerance: float, polish: bool = False) -> SurfaceReconstructor | None:
    """Fine-tune ``previous``'s network on (n, 3) ``points``; None when it cannot warm-start.

    tolerance : mm within which a new point counts as one the previous fit saw (a voxel).
    polish : train up to ``polish_epochs`` with ``polish_patience`` on ``polish_train_points``
        samples, else ``final_epochs`` with the MLP's own patience on ``max_train_points``.
    """
    if not hasattr(previous, "mlp_"):
        return None  # loaded from disk: the ONNX map can mesh but not train
    embedding = SurfaceEmbedding(n_neighbors=previous.n_neighbors_,
                                 random_state=params.seed).fit(points)
    support = points[embedding.support_]
    mine, theirs = shared_points(previous, support, tolerance)
    if len(mine) < max(20, MIN_SHARED * len(support)):
        log.debug("warm start refused: %d of %d points shared", len(mine), len(support))
        return None
    apply, residual = align_embedding(embedding.embedding_[mine], previous.embedding_[theirs])
    extent = float(np.ptp(previous.embedding_, axis=0).max())
    if residual > MAX_ALIGN_ERROR * extent:
        log.debug("warm start refused: alignment residual %.3g of extent %.3g", residual, extent)
        return None
    embedding.embedding_ = apply(embedding.embedding_)
    mlp = copy.deepcopy(previous.mlp_)
    if polish:
        mlp.set_params(final_epochs=params.polish_epochs, patience=params.polish_patience,
                       max_train_points=params.polish_train_points)
    else:
        mlp.set_params(final_epochs=params.final_epochs, max_train_points=params.max_train_points)
    mlp.fine_tune(embedding.embedding_, support)
    return _assemble(embedding, points, mlp, params)
