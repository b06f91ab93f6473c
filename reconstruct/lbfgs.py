"""Full-batch L-BFGS for a small torch net: torch gives the loss and gradient, scipy steps.

scipy's compiled L-BFGS-B loop costs less per iteration than ``torch.optim.LBFGS`` on the
adaptive search's tiny nets (measured when it came in: see the commit history), and it spares
the import of ``torch._dynamo`` that torch's optimisers trigger on first use.
"""

from __future__ import annotations

import numpy as np

from .networks import load_torch, mse


class FlatParameters:
    """A net's parameters and gradients as views into two flat float64 buffers, so that
    scipy reads and writes them without a copy per tensor. On exit every parameter gets its
    own storage back and its gradient is dropped."""

    def __init__(self, net):
        self.net = net
        self.params = list(net.parameters())

    def __enter__(self) -> FlatParameters:
        torch = load_torch()
        total = sum(p.numel() for p in self.params)
        values = torch.empty(total, dtype=torch.float64)
        grads = torch.zeros(total, dtype=torch.float64)
        offset = 0
        with torch.no_grad():
            for p in self.params:
                k = p.numel()
                values[offset : offset + k] = p.reshape(-1)
                p.data = values[offset : offset + k].view_as(p)
                p.grad = grads[offset : offset + k].view_as(p)
                offset += k
        self.values, self.grads = values.numpy(), grads.numpy()  # share the tensors' memory
        return self

    def __exit__(self, *exc) -> None:
        for p in self.params:
            p.data = p.data.clone()
            p.grad = None

    def get(self) -> np.ndarray:
        return self.values.copy()

    def set(self, theta: np.ndarray) -> None:
        self.values[:] = theta

    def loss_and_gradient(self, x, y):
        """f(theta) → (mean squared error of net(x) against y, its gradient (p,))."""
        torch = load_torch()

        def evaluate(theta):
            self.set(theta)
            self.grads[:] = 0.0
            loss = torch.nn.functional.mse_loss(self.net(x), y)
            loss.backward()
            value = loss.item()
            if not np.isfinite(value):
                return np.inf, np.zeros_like(self.grads)
            return value, self.grads.copy()

        return evaluate


def train_lbfgs(net, train, validation, max_epochs: int, steps_per_epoch: int,
                patience: int) -> tuple[float, int]:
    """Train ``net`` in place on ``train`` = (x, y) tensors; one epoch is ``steps_per_epoch``
    iterations (curvature history kept across epochs). After each epoch the validation MSE is
    checked; training stops after ``patience`` epochs without improvement, and the net is left
    at its best validation weights. Returns (best validation MSE, epochs run)."""
    from scipy.optimize import minimize

    with FlatParameters(net) as flat:
        best = {"mse": mse(net, *validation), "theta": flat.get(), "stale": 0, "epochs": 0,
                "iterations": 0}

        def end_of_epoch(theta) -> bool:
            """Score the epoch ending at theta; True when training should stop."""
            best["epochs"] += 1
            flat.set(theta)
            val = mse(net, *validation)
            if not np.isfinite(val):
                return True
            if val < best["mse"]:
                best.update(mse=val, theta=theta.copy(), stale=0)
                return False
            best["stale"] += 1
            return best["stale"] >= patience

        def end_of_iteration(intermediate_result):
            best["iterations"] += 1
            if best["iterations"] % steps_per_epoch == 0 and end_of_epoch(intermediate_result.x):
                raise StopIteration

        result = minimize(
            flat.loss_and_gradient(*train), flat.get(), jac=True, method="L-BFGS-B",
            callback=end_of_iteration,
            options={"maxiter": max_epochs * steps_per_epoch,
                     "maxfun": max_epochs * steps_per_epoch * 5 // 4,
                     "maxcor": 20, "ftol": 1e-15, "gtol": 1e-10},
        )
        if best["iterations"] % steps_per_epoch:  # converged inside an epoch: score its end
            end_of_epoch(result.x)
        flat.set(best["theta"])
    return best["mse"], best["epochs"]
