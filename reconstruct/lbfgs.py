"""Full-batch L-BFGS for several small MLPs at once: one batched program per step.

The adaptive search trains dozens of tiny nets (a 2-10-14-3 net has 229 parameters) whose
every step costs far more in Python and dispatch overhead than in arithmetic: a loss and
gradient of one such net on 1,360 points took 0.3–0.9 ms in torch, nearly all of it overhead.
Here B nets of the same depth are trained together: their weights are stacked and padded to the
widest net of each layer (`BatchedMLP`; padding is held at zero by a mask, so every net computes
exactly its own function), one batched forward/backward gives all B losses and gradients, and
the L-BFGS steps (two-loop recursion, backtracking Armijo line search with a step length per
net) run as numpy array operations over the B nets. Each net keeps its own curvature history,
step length, early stopping and best weights: the nets do not interact, they only share the
overhead.

Early stopping is on the validation MSE after every epoch of ``steps_per_epoch`` iterations;
a net stops after ``patience`` epochs without improvement (or when no step lowers its training
error) and is left at its best validation weights.
"""

from __future__ import annotations

import numpy as np

from .networks import load_torch

HISTORY = 10  # curvature pairs kept per net (scipy's default; 20 before: same fits, less work)
ARMIJO = 1e-4
MAX_BACKTRACKS = 12


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


def _direction(g, S, Y, rho, gamma, count, head):
    """L-BFGS two-loop recursion for every net: (B, P) search directions -H g."""
    m = S.shape[0]
    order = [(head - 1 - k) % m for k in range(min(count, m))]  # newest first
    q = g.copy()
    alphas = []
    for i in order:
        a = rho[i] * np.einsum("bp,bp->b", S[i], q)
        q -= a[:, None] * Y[i]
        alphas.append(a)
    r = gamma[:, None] * q
    for i, a in zip(reversed(order), reversed(alphas), strict=True):
        b = rho[i] * np.einsum("bp,bp->b", Y[i], r)
        r += S[i] * (a - b)[:, None]
    return -r


def train_lbfgs(nets, activation: str, train, validation, max_epochs: int,
                steps_per_epoch: int, patience: int, plateau: float = 0.0,
                dtype=np.float64) -> list[tuple[float, int]]:
    """Train the torch ``nets`` (same depth) in place, together, on ``train`` = (x, y) tensors;
    one epoch is ``steps_per_epoch`` iterations (curvature history kept across epochs). After
    each epoch every net's validation MSE is checked; a net stops after ``patience`` epochs
    without improvement, or once an epoch lowers its training MSE by less than the fraction
    ``plateau`` (converged), and is left at its best validation weights.
    Returns [(best validation MSE, epochs run)] per net."""
    model = BatchedMLP(nets, activation, dtype)
    x, y, xv, yv = (np.asarray(t, dtype=dtype) for t in (*train, *validation))
    theta = model.theta
    n_nets, size = theta.shape
    f, g = model.losses_and_gradients(theta, x, y, np.arange(n_nets))
    best_val = model.losses(theta, xv, yv)
    best_val[~np.isfinite(best_val)] = np.inf
    best_theta = theta.copy()
    stale = np.zeros(n_nets, dtype=int)
    epochs = np.zeros(n_nets, dtype=int)
    active = np.isfinite(f)
    pending = np.zeros(n_nets, dtype=bool)  # moved since the last validation check

    epoch_start = f.copy()

    def end_of_epoch():
        nonlocal best_val, stale, active, pending, epoch_start
        active &= ~pending | (f < (1.0 - plateau) * epoch_start)
        epoch_start = np.where(pending, f, epoch_start)
        val = model.losses(theta, xv, yv)
        better = pending & np.isfinite(val) & (val < best_val)
        best_val = np.where(better, val, best_val)
        best_theta[better] = theta[better]
        epochs[:] += pending
        stale = np.where(better, 0, stale + pending)
        active &= (stale < patience) & np.isfinite(val)
        pending = np.zeros(n_nets, dtype=bool)

    S, Y = np.zeros((HISTORY, n_nets, size)), np.zeros((HISTORY, n_nets, size))
    rho = np.zeros((HISTORY, n_nets))
    gamma = 1.0 / np.maximum(np.abs(g).sum(1), 1e-12)  # first step: unit l1 length
    count = head = 0
    for iteration in range(1, int(max_epochs) * int(steps_per_epoch) + 1):
        d = _direction(g, S, Y, rho, gamma, count, head)
        slope = np.einsum("bp,bp->b", g, d)
        downhill = slope < 0
        d[~downhill] = -g[~downhill]  # not a descent direction: steepest descent
        slope = np.where(downhill, slope, -np.einsum("bp,bp->b", g, g))
        d[~active] = 0.0
        step = np.ones(n_nets)
        ok = ~active
        trial, f_new, g_new = theta.copy(), f.copy(), g.copy()
        for _ in range(MAX_BACKTRACKS):  # only the nets still looking for a step are computed
            rows = np.flatnonzero(~ok)
            trial[rows] = theta[rows] + step[rows, None] * d[rows]
            f_new[rows], g_new[rows] = model.losses_and_gradients(trial[rows], x, y, rows)
            ok = ~active | (np.isfinite(f_new) & (f_new <= f + ARMIJO * step * slope))
            if ok.all():
                break
            step = np.where(ok, step, 0.25 * step)
        moved = ok & active
        active &= ok  # no step lowers the training error: converged (or stalled)
        pending |= moved
        s, yk = trial - theta, g_new - g
        sy, yy = np.einsum("bp,bp->b", s, yk), np.einsum("bp,bp->b", yk, yk)
        good = moved & (sy > 1e-10 * yy)
        theta = np.where(moved[:, None], trial, theta)
        f = np.where(moved, f_new, f)
        g = np.where(moved[:, None], g_new, g)
        S[head], Y[head] = np.where(good[:, None], s, 0.0), np.where(good[:, None], yk, 0.0)
        rho[head] = np.where(good, 1.0 / np.where(good, sy, 1.0), 0.0)
        gamma = np.where(good, sy / np.maximum(yy, 1e-300), gamma)
        head, count = (head + 1) % HISTORY, count + 1
        if iteration % steps_per_epoch == 0:
            end_of_epoch()
        if not active.any():
            break
    if pending.any():  # stopped inside an epoch: score where it ended
        end_of_epoch()
    model.write_back(best_theta)
    return [(float(v), int(e)) for v, e in zip(best_val, epochs, strict=True)]
