"""The small torch MLPs the adaptive search trains: building, growing, averaging, scoring.

Nets are plain float64 ``torch.nn.Sequential`` stacks of Linear and activation layers with a
linear output, so that they train, pickle and export to ONNX alike.
"""

from __future__ import annotations

import contextlib
import copy

import numpy as np

from .threads import single_threaded


def load_torch():
    import torch  # training only; inference never imports torch

    return torch


def activation_layer(name: str):
    nn = load_torch().nn
    return {"tanh": nn.Tanh, "sigmoid": nn.Sigmoid, "relu": nn.ReLU, "elu": nn.ELU,
            "softplus": nn.Softplus}[name]()


def build(layers: tuple[int, ...], activation: str, n_in: int, n_out: int, generator):
    """A float64 MLP n_in → layers… → n_out with a linear output, seeded initialisation."""
    torch = load_torch()
    modules, width = [], n_in
    for size in layers:
        modules += [torch.nn.Linear(width, size), activation_layer(activation)]
        width = size
    modules.append(torch.nn.Linear(width, n_out))
    net = torch.nn.Sequential(*modules).double()
    with torch.no_grad():
        for module in net:
            if isinstance(module, torch.nn.Linear):
                bound = 1.0 / np.sqrt(module.in_features)
                module.weight.uniform_(-bound, bound, generator=generator)
                module.bias.uniform_(-bound, bound, generator=generator)
    return net


def n_parameters(layers, n_in: int = 2, n_out: int = 3) -> int:
    """Weights and biases of an n_in → layers… → n_out MLP."""
    widths = [n_in, *layers, n_out]
    return sum((a + 1) * b for a, b in zip(widths[:-1], widths[1:], strict=True))


def linears(net):
    return [m for m in net if isinstance(m, load_torch().nn.Linear)]


def widen(net, layers, activation, n_in, n_out, generator):
    """``net`` plus one neuron in its last hidden layer, initialised as in a new net, with zero
    outgoing weights: the function is kept, and a projected fit (`lbfgs`) solves the new
    neuron's output weights at its first evaluation, so the wider net starts at least as good
    as the narrower one (least squares with one more column)."""
    torch = load_torch()
    wider = build(layers, activation, n_in, n_out, generator)
    old, new = linears(net), linears(wider)
    with torch.no_grad():
        for a, b in zip(old[:-2], new[:-2], strict=True):  # earlier layers: unchanged
            b.weight.copy_(a.weight)
            b.bias.copy_(a.bias)
        k = old[-2].out_features
        new[-2].weight[:k] = old[-2].weight
        new[-2].bias[:k] = old[-2].bias
        new[-1].weight.zero_()
        new[-1].weight[:, :k] = old[-1].weight
        new[-1].bias.copy_(old[-1].bias)
    return wider


def deepen(net, layers, activation, n_in, n_out, generator):
    """A net with one more hidden layer whose earlier layers start from ``net``'s."""
    torch = load_torch()
    deeper = build(layers, activation, n_in, n_out, generator)
    with torch.no_grad():
        for a, b in zip(linears(net)[:-1], linears(deeper)[:-2], strict=True):
            b.weight.copy_(a.weight)
            b.bias.copy_(a.bias)
    return deeper


def mean_of(*nets):
    """One MLP computing the mean of nets of the same architecture: their hidden layers side by
    side (block-diagonal weights), the output layer divided by their number. A plain
    ``Sequential``, so it trains, pickles and exports like any other net."""
    torch = load_torch()
    modules = []
    groups = list(zip(*nets, strict=True))
    linear_ids = [i for i, group in enumerate(groups) if isinstance(group[0], torch.nn.Linear)]
    with torch.no_grad():
        for i, group in enumerate(groups):
            if not isinstance(group[0], torch.nn.Linear):
                modules.append(copy.deepcopy(group[0]))
                continue
            if i == linear_ids[0]:
                weight = torch.cat([m.weight for m in group])
                bias = torch.cat([m.bias for m in group])
            elif i == linear_ids[-1]:
                weight = torch.cat([m.weight for m in group], dim=1) / len(group)
                bias = sum(m.bias for m in group) / len(group)
            else:
                weight = torch.block_diag(*(m.weight for m in group))
                bias = torch.cat([m.bias for m in group])
            layer = torch.nn.Linear(weight.shape[1], weight.shape[0]).double()
            layer.weight.copy_(weight)
            layer.bias.copy_(bias)
            modules.append(layer)
    return torch.nn.Sequential(*modules)


def mse(net, x, y) -> float:
    torch = load_torch()
    with torch.no_grad():
        return float(torch.mean((net(x) - y) ** 2))


@contextlib.contextmanager
def one_torch_thread():
    """Tiny nets on shared cores: one thread is faster and stable (measured 10–50× swings), for
    torch and for the BLAS and OpenMP pools (numpy, scipy) whatever the shell sets."""
    torch = load_torch()
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with single_threaded():
            yield
    finally:
        torch.set_num_threads(previous)
