"""The written-out loss gradients of `reconstruct.lbfgs` and its solved output layer."""

import numpy as np
import pytest
import torch

from reconstruct.lbfgs import ProjectedMLP, train_lbfgs
from reconstruct.mlp import ACTIVATIONS
from reconstruct.networks import build, mse


def samples(n=300, seed=0):
    generator = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 2, dtype=torch.float64, generator=generator)
    y = torch.stack([torch.sin(2 * x[:, 0]), x[:, 0] * x[:, 1], torch.cos(x[:, 1])], 1)
    return x, y + 0.01 * torch.randn(n, 3, dtype=torch.float64, generator=generator)


@pytest.mark.parametrize("activation", ACTIVATIONS)
@pytest.mark.parametrize("layers", [(4,), (3, 5)])
@pytest.mark.parametrize("decay", [0.0, 0.01])
def test_gradient_matches_central_differences(activation, layers, decay):
    x, y = samples()
    net = build(layers, activation, 2, 3, torch.Generator().manual_seed(1))
    flat = ProjectedMLP(net, dtype="float64")
    theta = flat.theta()
    evaluate = flat.loss_and_gradient(x, y, decay)
    _, gradient = evaluate(theta)
    numeric = np.empty_like(theta)
    for i in range(len(theta)):
        step = np.zeros_like(theta)
        step[i] = 1e-5
        numeric[i] = (evaluate(theta + step)[0] - evaluate(theta - step)[0]) / 2e-5
    assert np.abs(numeric - gradient).max() <= 1e-6 * np.abs(gradient).max()


@pytest.mark.parametrize("activation", ACTIVATIONS)
def test_single_precision_hidden_passes_give_the_double_loss_and_gradient(activation):
    x, y = samples()
    net = build((6, 4), activation, 2, 3, torch.Generator().manual_seed(2))
    theta = ProjectedMLP(net).theta()
    value, gradient = ProjectedMLP(net, dtype="float32").loss_and_gradient(x, y)(theta)
    exact, exact_gradient = ProjectedMLP(net, dtype="float64").loss_and_gradient(x, y)(theta)
    assert value == pytest.approx(exact, rel=1e-5)
    assert np.abs(gradient - exact_gradient).max() <= 1e-3 * np.abs(exact_gradient).max()


def test_projected_output_is_the_least_squares_fit_of_the_hidden_layer():
    x, y = samples()
    net = build((8,), "tanh", 2, 3, torch.Generator().manual_seed(3))
    flat = ProjectedMLP(net, dtype="float64")
    theta = flat.theta()
    flat.set(theta, flat.output_for(theta, x, y))
    with torch.no_grad():
        hidden = torch.cat([net[1](net[0](x)), torch.ones(len(x), 1, dtype=x.dtype)], 1)
        best = torch.linalg.lstsq(hidden, y).solution
        least = float(((hidden @ best - y) ** 2).mean())
    assert mse(net, x, y) == pytest.approx(least, rel=1e-6)


def test_training_lowers_the_error_and_keeps_the_best_validation_weights():
    x, y = samples(400)
    train, validation = (x[:340], y[:340]), (x[340:], y[340:])
    net = build((10,), "tanh", 2, 3, torch.Generator().manual_seed(4))
    before = mse(net, *validation)
    best, epochs = train_lbfgs(net, train, validation, max_epochs=30, steps_per_epoch=5,
                               patience=4)
    assert best == pytest.approx(mse(net, *validation), rel=1e-12)  # left at its best weights
    assert best < 0.2 * before
    assert 1 <= epochs <= 30


def test_weight_decay_adds_the_hidden_weights_squares_not_their_biases():
    x, y = samples()
    net = build((3, 5), "tanh", 2, 3, torch.Generator().manual_seed(4))
    flat = ProjectedMLP(net, dtype="float64")
    theta = flat.theta()
    plain, _ = flat.loss_and_gradient(x, y)(theta)
    decayed, _ = flat.loss_and_gradient(x, y, 0.5)(theta)
    weights = sum(float((layer.weight ** 2).sum()) for layer in flat.hidden)
    assert decayed - plain == pytest.approx(0.5 * weights, rel=1e-12)
