"""Full-batch L-BFGS for the adaptive search's small MLPs: numpy gradients, scipy's steps.

The search trains dozens of tiny nets (a 2-10-14-3 net has 229 parameters) whose every step
cost more in dispatch than in arithmetic: a loss and gradient of one such net on 1,360 points
took 0.3–0.9 ms through torch's autograd. `BatchedMLP` computes them in numpy with the
back-propagation written out (a handful of matrix products per layer, no graph), for one net
or for several of the same depth stacked and zero-padded (a mask holds the padding at zero,
so each computes exactly its own function); scipy's compiled L-BFGS-B takes the steps
(`train_lbfgs`, one net at a time, as before: the same optimizer, line search and options).

A batched L-BFGS (B nets per step, numpy two-loop recursion, Armijo backtracking) was tried:
the search ran about as fast (the steps are compute-bound once autograd is gone) and the
meshes of bench/quality.py came out up to 2× worse in Chamfer-L1 (S-curve σ 0.5 %: a
one-layer net chosen), so scipy's line search stays.

Early stopping is on the validation MSE after every epoch of ``steps_per_epoch`` iterations;
a net stops after ``patience`` epochs without improvement and is left at its best validation
weights.
"""

from __future__ import annotations

import numpy as np

from .networks import load_torch

HISTORY = 20  # L-BFGS-B's maxcor: curvature pairs kept


def activation_functions(name: str):
    """(f(z), its derivative from (z, f(z))) in numpy, for a hidden activation of
    `networks.activation_layer` (torch's defaults: elu alpha 1, softplus beta 1 threshold 20)."""
    if name == "tanh":
        return np.tanh, lambda z, a: 1.0 - a * a
    if name == "sigmoid":
        def sigmoid(z):
            return 0.5 * (1.0 + np.tanh(0.5 * z))
        return sigmoid, lambda z, a: a * (1.0 - a)
    if name == "relu":
        return (lambda z: np.maximum(z, 0.0)), (lambda z, a: (z > 0).astype(z.dtype))
    if name == "elu":  # torch's default alpha = 1
        return (lambda z: np.where(z > 0, z, np.expm1(np.minimum(z, 0.0))),
                lambda z, a: np.where(z > 0, 1.0, a + 1.0))
    if name == "softplus":  # torch's default beta = 1, threshold = 20
        return (lambda z: np.where(z > 20, z, np.log1p(np.exp(np.minimum(z, 20.0)))),
                lambda z, a: 0.5 * (1.0 + np.tanh(0.5 * z)))
    raise ValueError(f"unknown activation {name!r}")


class BatchedMLP:
    """B float64 MLPs ``n_in → widths… → n_out`` of the same depth, stacked and zero-padded.

    ``theta`` (B, P) holds each net's parameters, ``mask`` (B, P) marks the real ones. Layer l
    is a weight (B, in_l, out_l) and a bias (B, 1, out_l) view of ``theta``."""

    def __init__(self, nets, activation: str, dtype=np.float64):
        torch = load_torch()
        self.f, self.df = activation_functions(activation)
        linears = [[m for m in net if isinstance(m, torch.nn.Linear)] for net in nets]
        depth = len(linears[0])
        if any(len(layers) != depth for layers in linears):
            raise ValueError("BatchedMLP needs nets of the same depth")
        self.nets, self.linears = nets, linears
        self.shapes = []  # (in_max, out_max) per layer
        for layer in range(depth):
            self.shapes.append((max(ls[layer].in_features for ls in linears),
                                max(ls[layer].out_features for ls in linears)))
        self.offsets = np.cumsum([0] + [(i + 1) * o for i, o in self.shapes])
        size = int(self.offsets[-1])
        theta = np.zeros((len(nets), size), dtype=dtype)
        mask = np.zeros((len(nets), size), dtype=dtype)
        with torch.no_grad():
            for b, layers in enumerate(linears):
                for weight, bias, layer in zip(self._views(theta), self._biases(theta), layers,
                                               strict=True):
                    weight[b, : layer.in_features, : layer.out_features] = layer.weight.numpy().T
                    bias[b, 0, : layer.out_features] = layer.bias.numpy()
                for weight, bias, layer in zip(self._views(mask), self._biases(mask), layers,
                                               strict=True):
                    weight[b, : layer.in_features, : layer.out_features] = 1.0
                    bias[b, 0, : layer.out_features] = 1.0
        self.theta, self.mask = theta, mask

    def _views(self, flat):
        return [flat[:, a : a + i * o].reshape(len(flat), i, o)
                for a, (i, o) in zip(self.offsets[:-1], self.shapes, strict=True)]

    def _biases(self, flat):
        return [flat[:, a + i * o : a + (i + 1) * o].reshape(len(flat), 1, o)
                for a, (i, o) in zip(self.offsets[:-1], self.shapes, strict=True)]

    def forward(self, theta, x, keep: bool = False):
        """theta (k, P), x (n, n_in) → (k, n, n_out); ``keep``: also the hidden layers'
        (pre-activations, activations)."""
        a, hidden = x, []
        for layer, (weight, bias) in enumerate(zip(self._views(theta), self._biases(theta),
                                                   strict=True)):
            z = np.matmul(a, weight)
            z += bias
            if layer == len(self.shapes) - 1:
                return (z, hidden) if keep else z
            a = self.f(z)
            if keep:
                hidden.append((z, a))

    def losses(self, theta, x, y):
        """(k,) mean squared errors of the nets at ``theta`` (k, P)."""
        diff = self.forward(theta, x) - y
        return np.einsum("bnm,bnm->b", diff, diff) / diff[0].size

    def losses_and_gradients(self, theta, x, y, rows):
        """((k,) MSEs, (k, P) their gradients) of the nets ``rows`` (k indices) at ``theta``
        (k, P): back-propagation by hand, as matrix products over the k nets."""
        out, hidden = self.forward(theta, x, keep=True)
        delta = out - y
        loss = np.einsum("bnm,bnm->b", delta, delta) / delta[0].size
        delta *= 2.0 / delta[0].size
        grad = np.empty_like(theta)
        weights, g_weights, g_biases = self._views(theta), self._views(grad), self._biases(grad)
        for layer in range(len(self.shapes) - 1, -1, -1):
            inputs = hidden[layer - 1][1] if layer else x
            np.matmul(np.swapaxes(inputs, -1, -2), delta, out=g_weights[layer])
            g_biases[layer][:, 0, :] = delta.sum(axis=1)
            if layer:
                z, a = hidden[layer - 1]
                delta = np.matmul(delta, np.swapaxes(weights[layer], 1, 2))
                delta *= self.df(z, a)
        grad *= self.mask[rows]
        return loss, grad

    def write_back(self, theta) -> None:
        """Copy each net's parameters from ``theta`` (B, P) into its torch net."""
        torch = load_torch()
        with torch.no_grad():
            for b, layers in enumerate(self.linears):
                for weight, bias, layer in zip(self._views(theta), self._biases(theta), layers,
                                               strict=True):
                    block = weight[b, : layer.in_features, : layer.out_features]
                    layer.weight.copy_(torch.from_numpy(block.T.astype(np.float64)))
                    layer.bias.copy_(torch.from_numpy(
                        bias[b, 0, : layer.out_features].astype(np.float64)))


def _train_one(model: BatchedMLP, x, y, xv, yv, max_epochs: int, steps_per_epoch: int,
               patience: int) -> tuple[np.ndarray, float, int]:
    """scipy's L-BFGS-B on the single net of ``model``: (best theta (1, P), its validation
    MSE, epochs run)."""
    from scipy.optimize import minimize

    rows, mask = np.arange(1), model.mask[0] > 0
    shape = model.theta.shape
    full = model.theta.copy()

    def evaluate(values):
        full[0, mask] = values
        loss, grad = model.losses_and_gradients(full, x, y, rows)
        if not np.isfinite(loss[0]):
            return np.inf, np.zeros_like(values)
        return float(loss[0]), grad[0, mask]

    def validation_mse(values) -> float:
        full[0, mask] = values
        return float(model.losses(full, xv, yv)[0])

    start = model.theta[0, mask]
    best = {"mse": validation_mse(start), "theta": start.copy(), "stale": 0, "epochs": 0,
            "iterations": 0}

    def end_of_epoch(values) -> bool:
        """Score the epoch ending at ``values``; True when training should stop."""
        best["epochs"] += 1
        val = validation_mse(values)
        if not np.isfinite(val):
            return True
        if val < best["mse"]:
            best.update(mse=val, theta=values.copy(), stale=0)
            return False
        best["stale"] += 1
        return best["stale"] >= patience

    def end_of_iteration(intermediate_result):
        best["iterations"] += 1
        if best["iterations"] % steps_per_epoch == 0 and end_of_epoch(intermediate_result.x):
            raise StopIteration

    result = minimize(
        evaluate, start, jac=True, method="L-BFGS-B", callback=end_of_iteration,
        options={"maxiter": max_epochs * steps_per_epoch,
                 "maxfun": max_epochs * steps_per_epoch * 5 // 4,
                 "maxcor": HISTORY, "ftol": 1e-15, "gtol": 1e-10},
    )
    if best["iterations"] % steps_per_epoch:  # converged inside an epoch: score its end
        end_of_epoch(result.x)
    theta = np.zeros(shape)
    theta[0, mask] = best["theta"]
    return theta, best["mse"], best["epochs"]


def train_lbfgs(nets, activation: str, train, validation, max_epochs: int,
                steps_per_epoch: int, patience: int) -> list[tuple[float, int]]:
    """Train each torch net of ``nets`` in place on ``train`` = (x, y) arrays or tensors by
    full-batch L-BFGS (scipy's L-BFGS-B, numpy loss and gradient); one epoch is
    ``steps_per_epoch`` iterations (curvature history kept across epochs). After each epoch
    the validation MSE is checked; a net stops after ``patience`` epochs without improvement
    and is left at its best validation weights.
    Returns [(best validation MSE, epochs run)] per net."""
    x, y, xv, yv = (np.asarray(t, dtype=np.float64) for t in (*train, *validation))
    results = []
    for net in nets:
        model = BatchedMLP([net], activation)
        theta, best, epochs = _train_one(model, x, y, xv, yv, int(max_epochs),
                                         int(steps_per_epoch), int(patience))
        model.write_back(theta)
        results.append((best, epochs))
    return results
