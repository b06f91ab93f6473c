"""Fitting one patch of a scan: warm-started from its earlier fit, at the scan's architecture, or
with the paper's search.

A fresh fit is `SurfaceReconstructor`'s: embed (Isomap / MLLE), grow the adaptive MLP, mesh; or,
once a patch of the scan has found an architecture, embed and train that architecture
(`AdaptiveMLP(hidden_layers=...)`). A warm start reuses the same patch's fitted network
(`SurfaceReconstructor.fit(points, warm_start=earlier)`: the new embedding aligned to the earlier
one, the network fine-tuned, no search). Measured: warm-starting a neighbouring patch from its
neighbour's network degrades along the chain, so a patch's first fit is always fresh; when too
few points are shared or the embeddings disagree, the fit starts fresh.
"""

from __future__ import annotations

import logging

from reconstruct.errors import WarmStartRefused
from reconstruct.mlp import AdaptiveMLP
from reconstruct.pipeline import SurfaceReconstructor

from ..plan import ReconstructionParams

log = logging.getLogger(__name__)

#: The engine keeps the better of each fit's two final trainings, not their mean: a patch's net
#: is fine-tuned again after more views, and the mean is twice as wide (faster, measured on
#: bench/scan.py).
FINAL_FIT = "better"
#: ... of two trainings (its searched weights and one fresh start), not the pipeline's three.
FINAL_STARTS = 1
#: ... and stops those trainings after 6 flat epochs of 5 iterations (bench/scan.py's vase with
#: it: 25.8 s in all, 99.9 % complete, denoise 0.463; the pipeline's 20 not measured there).
FINAL_PATIENCE = 6


def _reconstructor(params: ReconstructionParams, mlp: AdaptiveMLP | None = None,
                   fine_tune: dict | None = None,
                   warm_tolerance: float | None = None) -> SurfaceReconstructor:
    return SurfaceReconstructor(
        lam=params.lam, depth=params.depth, max_layers=params.max_layers,
        max_neurons=params.max_neurons, random_state=params.seed, mlp=mlp, fine_tune=fine_tune,
        warm_tolerance=warm_tolerance, atlas="never",  # a sector is the engine's own chart
        up=None,  # oriented outwards with its patch (reconstruct.patches)
    )


def fit_fresh(points, params: ReconstructionParams) -> SurfaceReconstructor:
    """The paper's whole pipeline on (n, 3) points with the plan's MLP limits."""
    mlp = AdaptiveMLP(
        max_layers=params.max_layers, max_neurons=params.max_neurons,
        max_epochs=params.max_epochs, final_epochs=params.final_epochs,
        max_train_points=params.max_train_points, final_fit=FINAL_FIT,
        final_starts=FINAL_STARTS, final_patience=FINAL_PATIENCE, random_state=params.seed,
    )
    return _reconstructor(params, mlp).fit(points)


def _training(params: ReconstructionParams, polish: bool) -> dict:
    """The final trainings' budget: ``polish_*`` for a polished fit, else the plan's."""
    if polish:
        return {"final_epochs": params.polish_epochs, "patience": params.polish_patience,
                "max_train_points": params.polish_train_points}
    return {"final_epochs": params.final_epochs, "max_train_points": params.max_train_points}


def fit_fixed(points, layers, params: ReconstructionParams,
              polish: bool = False) -> SurfaceReconstructor:
    """Embed (n, 3) points and train an MLP of hidden ``layers`` (no search); ``polish``: with
    the ``polish_*`` epochs, patience and samples."""
    training = _training(params, polish)
    patience = training.pop("patience", FINAL_PATIENCE)  # one patience: the final fits'
    mlp = AdaptiveMLP(hidden_layers=tuple(layers), max_layers=len(layers),
                      max_neurons=max(layers), final_fit=FINAL_FIT, final_starts=FINAL_STARTS,
                      random_state=params.seed,
                      patience=patience, final_patience=patience, **training)
    return _reconstructor(params, mlp).fit(points)


def fit_warm(points, previous: SurfaceReconstructor, params: ReconstructionParams,
             tolerance: float, polish: bool = False) -> SurfaceReconstructor | None:
    """Fine-tune ``previous``'s network on (n, 3) ``points``; None when it cannot warm-start.

    tolerance : mm within which a new point counts as one the previous fit saw (a voxel).
    polish : train up to ``polish_epochs`` with ``polish_patience`` on ``polish_train_points``
        samples, else ``final_epochs`` with the network's own patience on ``max_train_points``.
    """
    try:
        model = _reconstructor(params, fine_tune=_training(params, polish),
                               warm_tolerance=tolerance)
        return model.fit(points, warm_start=previous)
    except WarmStartRefused as refused:
        log.debug("warm start refused: %s", refused)
        return None


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
