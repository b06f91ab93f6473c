"""The adaptive MLP trained at a given architecture, without the search.

A scan's patches are pieces of one object: the paper's architecture search (`AdaptiveMLP`) runs
on the first patches, and the others train the architecture it found — the search's own final
stage (`AdaptiveMLP._train_final`: two starts trained to convergence, the better kept) without
its ~30 trial networks. Measured on the simulated vase: the same accuracy per patch in about
half the time, and no patch left with a collapsed one-layer network when its search stops
early.

Stopgap: this reaches into `AdaptiveMLP`'s private steps. The public hook it stands for is an
``AdaptiveMLP(hidden_layers=...)`` parameter that skips the search (asked of reconstruct/).
"""

from __future__ import annotations

from reconstruct.mlp import AdaptiveMLP
from reconstruct.networks import build, one_torch_thread
from reconstruct.surface_map import OnnxSurfaceMap


class FixedArchitectureMLP(AdaptiveMLP):
    """`AdaptiveMLP` whose ``hidden_layers`` are given (tuple of widths); ``fit`` trains them.

    Fitted attributes as `AdaptiveMLP` (``hidden_layers_`` equals ``hidden_layers``)."""

    def __init__(self, hidden_layers=(16, 8), activation: str = "tanh", final_epochs: int = 150,
                 steps_per_epoch: int = 20, patience: int = 6, test_weight: float = 0.5,
                 max_train_points: int = 6000, final_fit: str = "mean",
                 random_state: int | None = 0):
        super().__init__(
            max_layers=len(hidden_layers), max_neurons=max(hidden_layers), activation=activation,
            final_epochs=final_epochs, steps_per_epoch=steps_per_epoch, patience=patience,
            final_patience=patience,  # no search here: its one patience is the final fits'
            test_weight=test_weight, max_train_points=max_train_points, final_fit=final_fit,
            random_state=random_state,
        )
        self.hidden_layers = hidden_layers

    def fit(self, uv, xyz) -> FixedArchitectureMLP:
        """uv : (n, 2) embedded points; xyz : (n, 3) their 3D positions. Returns self."""
        self._check_params()
        rng, generator = self._random()
        tensors = self._samples(uv, xyz, rng, new_normalisation=True)
        n_in, n_out = (t.shape[1] for t in tensors["train"])
        self.history_ = []
        self.hidden_layers_ = tuple(int(w) for w in self.hidden_layers)
        with one_torch_thread():
            net = build(self.hidden_layers_, self.activation, n_in, n_out, generator)
            net = self._train_final(net, tensors, generator)
        self.torch_model_ = net.eval()
        self._store_errors(tensors)
        self.surface_map_ = OnnxSurfaceMap(self._export(net))
        return self

