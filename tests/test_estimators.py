"""Every estimator of reconstruct/ honours the scikit-learn contract: ``__init__`` stores its
parameters and nothing else, `get_params` / `set_params` / `clone` round-trip them, `fit` returns
self, leaves the parameters as they were and sets only attributes that end in ``_`` (or private
caches starting with ``_``)."""

import inspect

import numpy as np
import pytest
import trimesh
from scipy.spatial import Delaunay
from sklearn.base import BaseEstimator, clone

from reconstruct.boundary import MultiDepthBoundary, PCABoundary
from reconstruct.embedding import SurfaceEmbedding
from reconstruct.mlp import AdaptiveMLP
from reconstruct.patches import PatchReconstructor, PatchSplit
from reconstruct.pipeline import SurfaceReconstructor
from reconstruct.spline import BoundarySpline

RNG = np.random.default_rng(0)
GRID = np.stack(np.meshgrid(np.linspace(0, 1, 20), np.linspace(0, 1, 20)), -1).reshape(-1, 2)
SHEET = np.c_[GRID, 0.1 * np.sin(3 * GRID[:, 0])] + RNG.normal(0, 0.005, (len(GRID), 3))
LOOP = np.c_[np.cos(np.linspace(0, 2 * np.pi, 40, endpoint=False)),
             np.sin(np.linspace(0, 2 * np.pi, 40, endpoint=False))]


def tube(n=3000):
    """(n, 3) points on a 40 mm radius, 80 mm tall tube about the z axis."""
    angle, z = RNG.uniform(0, 2 * np.pi, n), RNG.uniform(0, 80, n)
    return np.c_[40 * np.cos(angle), 40 * np.sin(angle), z]


class PlaneMesh(BaseEstimator):
    """Cheap patch reconstructor: Delaunay of the points in their best-fit plane."""

    def fit(self, points):
        centred = points - points.mean(0)
        basis = np.linalg.svd(centred, full_matrices=False)[2][:2]
        self.mesh_ = trimesh.Trimesh(points, Delaunay(centred @ basis.T).simplices,
                                     process=False)
        return self


CASES = {
    "SurfaceEmbedding": (SurfaceEmbedding(random_state=0), (SHEET,)),
    "AdaptiveMLP": (AdaptiveMLP(max_layers=1, max_neurons=2, max_epochs=2, final_epochs=2),
                    (GRID, SHEET)),
    "AdaptiveMLP(hidden_layers)": (AdaptiveMLP(hidden_layers=(3,), final_epochs=2),
                                   (GRID, SHEET)),
    "MultiDepthBoundary": (MultiDepthBoundary(), (GRID,)),
    "PCABoundary": (PCABoundary(), (GRID,)),
    "BoundarySpline": (BoundarySpline(), (LOOP,)),
    "SurfaceReconstructor": (SurfaceReconstructor(max_layers=1, max_neurons=3), (SHEET,)),
    "PatchReconstructor": (PatchReconstructor(n_sectors=4, cap=False,
                                              reconstructor=PlaneMesh()), (tube(),)),
}


def init_parameters(estimator) -> list[str]:
    signature = inspect.signature(type(estimator).__init__)
    return [name for name in signature.parameters if name != "self"]


@pytest.mark.parametrize("estimator", [case[0] for case in CASES.values()] + [PatchSplit()],
                         ids=[*CASES, "PatchSplit"])
def test_parameters_round_trip(estimator):
    names = init_parameters(estimator)
    params = estimator.get_params(deep=False)
    assert sorted(params) == sorted(names)
    assert sorted(vars(estimator)) == sorted(names)  # __init__ stores its parameters only
    copy = clone(estimator)
    assert type(copy) is type(estimator) and copy is not estimator
    assert repr(copy.get_params(deep=False)) == repr(params)
    assert copy.set_params(**params) is copy


@pytest.mark.parametrize("case", list(CASES))
def test_fit_returns_self_and_sets_only_trailing_underscore_attributes(case):
    estimator, data = CASES[case]
    estimator = clone(estimator)
    before = repr(estimator.get_params(deep=False))
    assert estimator.fit(*data) is estimator
    assert repr(estimator.get_params(deep=False)) == before  # fit never changes a parameter
    params = set(init_parameters(estimator))
    added = set(vars(estimator)) - params
    public = sorted(a for a in added if not a.startswith("_"))
    assert public and all(a.endswith("_") for a in public), public
    refit = clone(estimator)  # a clone of a fitted estimator is unfitted
    assert not [a for a in vars(refit) if a.endswith("_")]


def test_warm_start_fit_sets_the_fitted_attributes_itself():
    first = SurfaceReconstructor(max_layers=1, max_neurons=3).fit(SHEET[::2])
    warm = SurfaceReconstructor(fine_tune={"final_epochs": 3}, warm_tolerance=0.02)
    assert warm.fit(SHEET, warm_start=first) is warm
    assert warm.hidden_layers_ == first.hidden_layers_ and warm.mlp_ is not first.mlp_
    assert warm.mlp_.final_epochs == 3 and first.mlp_.final_epochs != 3
    assert warm.mlp_.history_[-1].get("fine_tune")
    assert len(warm.points_) == len(warm.embedding_) and len(warm.mesh_.faces) > 0
