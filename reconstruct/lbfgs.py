"""Full-batch L-BFGS for a small MLP with its linear output layer solved exactly.

Variable projection (Golub & Pereyra): for given hidden layers the output layer that fits best
is a linear least-squares solution, so every evaluation solves it (normal equations of the last
hidden layer's activations plus a bias column; a fixed ridge of 1e-8 per sample keeps twin
neurons solvable) and L-BFGS moves only the hidden weights. The gradient with respect to them
is the plain back-propagated gradient at the solved output (the output's own gradient is zero
there). Training every layer together instead (measured as the final fits after a projected
search) gave bench.quality a median Chamfer-L1 ratio of 0.963 against 0.938 projected.

The loss and gradient are written out in numpy (forward, then back-propagation through the
activation's derivative) instead of taken from torch's autograd: on these tiny nets the graph
bookkeeping, then torch's per-call dispatch, cost more than the arithmetic. scipy's compiled
L-BFGS-B takes the steps.

The hidden layers run in single precision (``HIDDEN_DTYPE``) and the projection in double:
the activations are the bulk of the arithmetic (float32 tanh vectorises, float64 does not), while
the normal equations of the output layer need double. Per evaluation 1.3× (1,360 samples) to
2× (5,100 samples, two layers) faster than all in double; the value differs by ~1e-8 and the
gradient by ~1e-4 relative, far below what early stopping resolves (`MIN_GAIN`).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dposv
from scipy.special import expit

from .networks import linears, load_torch

RIDGE = 1e-8
#: Relative drop of the validation error that counts as progress for early stopping. The
#: held-out error of a fit near convergence is mostly the noise and creeps down by less than
#: this for hundreds of iterations (the best weights are still kept). Measured at 20,000
#: points σ 1 % (bench/quality.py's S-curve, saddle, half torus): final fits 2–5× shorter and
#: Chamfer-L1 0.00472 → 0.00417, 0.00111 → 0.00101, 0.00389 → 0.00373.
MIN_GAIN = 1e-3
#: Precision of the hidden layers' forward and backward passes (the projection is in double).
HIDDEN_DTYPE = "float32"


#: Each hidden activation (by its torch module's name) in numpy, with its derivative d h / d z
#: as a function of (z, h); the dtype of z is kept.
NUMPY_ACTIVATIONS = {
    "Tanh": (np.tanh, None),  # h' = 1 - h², taken in place in `loss_and_gradient`
    "Sigmoid": (expit, lambda z, h: h * (1.0 - h)),
    "ReLU": (lambda z: np.maximum(z, 0), lambda z, h: (z > 0).astype(z.dtype)),
    "ELU": (lambda z: np.where(z > 0, z, np.expm1(z)), lambda z, h: np.where(z > 0, 1, h + 1)),
    "Softplus": (lambda z: np.logaddexp(0, z), lambda z, h: expit(z)),
}


class ProjectedMLP:
    """A Sequential MLP's hidden weights as one flat float64 vector ``theta`` (each layer's
    (in, out) weight matrix then its bias: together its (in + 1, out) matrix acting on the
    inputs with a ones column), its output layer solved for them. ``dtype``: the hidden
    passes' precision, "float32" or "float64" (None: ``HIDDEN_DTYPE``).

    The passes are numpy on the net's weights (the torch net is read once and written back by
    `set`): per evaluation numpy pays about 1 µs a call where torch pays 5–10, and these nets
    are small enough for that to be most of the time (0.96 → 0.60 ms, 1,360 samples, layers
    (15, 20))."""

    def __init__(self, net, dtype: str | None = None):
        torch = load_torch()
        self.net = net
        self.dtype = np.dtype(dtype or HIDDEN_DTYPE)
        layers = linears(net)
        self.hidden, self.output = layers[:-1], layers[-1]
        activation = next(m for m in net if not isinstance(m, torch.nn.Linear))
        self.activation, self.derivative = NUMPY_ACTIVATIONS[type(activation).__name__]
        self.tanh = self.derivative is None
        self.shapes = [(layer.in_features, layer.out_features) for layer in self.hidden]
        self.cached = None  # (theta, output weights (w + 1, n_out)) last solved

    def theta(self) -> np.ndarray:
        parts = []
        for layer in self.hidden:
            parts += [layer.weight.detach().numpy().T.reshape(-1), layer.bias.detach().numpy()]
        return np.concatenate(parts).astype(np.float64)

    def _views(self, flat) -> list:
        """The (in + 1, out) matrix of each hidden layer: views of the flat array ``flat``."""
        out, offset = [], 0
        for a, b in self.shapes:
            out.append(flat[offset : offset + (a + 1) * b].reshape(a + 1, b))
            offset += (a + 1) * b
        return out

    def loss_and_gradient(self, x, y, decay: float = 0.0):
        """f(theta) → (MSE on (x, y) plus the ridge term, plus ``decay`` times the sum of the
        hidden layers' squared weights (not their biases), its gradient); x (n, n_in), y
        (n, n_out) arrays or tensors.

        Each layer's input keeps a ones column in a buffer of its own, so one product gives its
        pre-activations and one its weights' and bias's gradient, written straight into the
        flat gradient; the last activations, their ones column and the targets share one double
        buffer, so one product gives the normal equations and their right-hand side."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        n, n_out = y.shape
        width = self.shapes[-1][1]
        inputs = [np.ones((n, a + 1), dtype=self.dtype) for a, _ in self.shapes]
        inputs[0][:, :-1] = x
        design = np.ones((n, width + 1 + n_out))  # [h, 1, y]
        design[:, width + 1 :] = y
        a = design[:, : width + 1]
        gradient = np.empty(sum((i + 1) * o for i, o in self.shapes), dtype=self.dtype)
        gradients = self._views(gradient)
        diagonal = np.arange(width + 1)
        ridge, scale = RIDGE * n, 1.0 / (n * n_out)

        def evaluate(theta):
            params = self._views(theta.astype(self.dtype))
            zs, hs = [], []
            with np.errstate(over="ignore", invalid="ignore"):
                for i, matrix in enumerate(params):
                    zs.append(inputs[i] @ matrix)
                    hs.append(self.activation(zs[-1]))
                    if i + 1 < len(params):
                        inputs[i + 1][:, :-1] = hs[-1]
                design[:, :width] = hs[-1]
                normal = a.T @ design  # (w + 1, w + 1 + n_out): gram | right-hand side
                normal[diagonal, diagonal] += ridge
                # Cholesky (LAPACK's dposv: a quarter of np.linalg.solve's call overhead)
                _, out, failed = dposv(normal[:, : width + 1], normal[:, width + 1 :])
                if failed:  # not positive definite: diverged
                    return np.inf, np.zeros_like(theta)
                residual = a @ out - y
                value = (float(np.vdot(residual, residual)) + ridge * float(np.vdot(out, out)))
                value *= scale
                if decay:
                    value += decay * sum(float(np.vdot(p[:-1], p[:-1])) for p in params)
            if not np.isfinite(value):
                return np.inf, np.zeros_like(theta)
            self.cached = (theta.copy(), out)
            delta = (residual @ (out[:-1].T * (2.0 * scale))).astype(self.dtype)
            for i in range(len(params) - 1, -1, -1):  # d loss / d activations of layer i
                h = hs[i]
                if self.tanh:  # delta * (1 - h²)
                    delta -= delta * h * h
                else:
                    delta *= self.derivative(zs[i], h)
                np.matmul(inputs[i].T, delta, out=gradients[i])
                if decay:
                    gradients[i][:-1] += (2.0 * decay) * params[i][:-1]
                if i:
                    delta = delta @ params[i][:-1].T
            return value, gradient.astype(np.float64)

        return evaluate

    def output_for(self, theta, x, y) -> np.ndarray:
        """The output weights (w + 1, n_out) for ``theta`` (cached from the last solve; else
        one evaluation on (x, y) solves them, NaN where it diverged)."""
        if self.cached is None or not np.array_equal(self.cached[0], theta):
            value, _ = self.loss_and_gradient(x, y)(theta)
            if not np.isfinite(value):  # nothing solved: the validation error says so
                return np.full((self.shapes[-1][1] + 1, np.shape(y)[1]), np.nan)
        return self.cached[1]

    def mse(self, theta, out, x, y) -> float:
        """Mean squared error of the net with ``theta`` and output weights ``out`` on (x, y),
        in double precision (the value the torch net gives once `set`)."""
        h = np.asarray(x, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            for matrix in self._views(theta):
                h = self.activation(h @ matrix[:-1] + matrix[-1])
            error = h @ out[:-1] + out[-1] - np.asarray(y, dtype=np.float64)
            return float(np.mean(error * error))

    def set(self, theta, out) -> None:
        """Copy ``theta`` and the output weights ``out`` (w + 1, n_out) into the net."""
        torch = load_torch()
        with torch.no_grad():
            for layer, matrix in zip(self.hidden, self._views(theta), strict=True):
                layer.weight.copy_(torch.from_numpy(matrix[:-1].T.copy()))
                layer.bias.copy_(torch.from_numpy(matrix[-1].copy()))
            out = torch.from_numpy(np.ascontiguousarray(out, dtype=np.float64))
            self.output.weight.copy_(out[:-1].T)
            self.output.bias.copy_(out[-1])


def train_lbfgs(net, train, validation, max_epochs: int, steps_per_epoch: int,
                patience: int, decay: float = 0.0) -> tuple[float, int]:
    """Train ``net`` in place on ``train`` = (x, y) tensors (``decay``: weight decay of the
    hidden weights, `ProjectedMLP.loss_and_gradient`); one epoch is ``steps_per_epoch``
    iterations (curvature history kept across epochs). After each epoch the validation MSE is
    checked; training stops after ``patience`` epochs without an improvement of ``MIN_GAIN``
    (relative), and the net is left at its best validation weights. Returns (best validation
    MSE, epochs run)."""
    from scipy.optimize import minimize

    x, y = (np.asarray(t, dtype=np.float64) for t in train)
    validation = tuple(np.asarray(t, dtype=np.float64) for t in validation)
    flat = ProjectedMLP(net)
    start = flat.theta()
    out = flat.output_for(start, x, y)
    best = {"mse": flat.mse(start, out, *validation), "theta": start, "out": out, "stale": 0,
            "epochs": 0, "iterations": 0}

    def end_of_epoch(theta) -> bool:
        """Score the epoch ending at theta; True when training should stop."""
        best["epochs"] += 1
        out = flat.output_for(theta, x, y)
        val = flat.mse(theta, out, *validation)
        if not np.isfinite(val):
            return True
        significant = val < best["mse"] * (1.0 - MIN_GAIN)
        if val < best["mse"]:
            best.update(mse=val, theta=theta.copy(), out=out.copy())
        best["stale"] = 0 if significant else best["stale"] + 1
        return best["stale"] >= patience

    def end_of_iteration(intermediate_result):
        best["iterations"] += 1
        if best["iterations"] % steps_per_epoch == 0 and end_of_epoch(intermediate_result.x):
            raise StopIteration

    result = minimize(
        flat.loss_and_gradient(x, y, decay), start, jac=True, method="L-BFGS-B",
        callback=end_of_iteration,
        options={"maxiter": max_epochs * steps_per_epoch,
                 "maxfun": max_epochs * steps_per_epoch * 5 // 4,
                 "maxcor": 20, "ftol": 1e-15, "gtol": 1e-10},
    )
    if best["iterations"] % steps_per_epoch:  # converged inside an epoch: score its end
        end_of_epoch(result.x)
    flat.set(best["theta"], best["out"])
    return best["mse"], best["epochs"]
