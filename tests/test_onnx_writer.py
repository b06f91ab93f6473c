"""The hand-written ONNX model of an MLP: valid for the onnx checker, and equal to the torch
network it was written from for every activation, deep nets and averaged (block) nets."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch

from reconstruct.mlp import ACTIVATIONS
from reconstruct.networks import build, linears, mean_of
from reconstruct.onnx_writer import mlp_model
from reconstruct.surface_map import OnnxSurfaceMap


def _write(net, activation, x_mean, x_scale, y_mean, y_scale) -> bytes:
    layers = [(m.weight.detach().numpy().T, m.bias.detach().numpy()) for m in linears(net)]
    return mlp_model(layers, activation, x_mean, x_scale, y_mean, y_scale)


@pytest.mark.parametrize("activation", ACTIVATIONS)
@pytest.mark.parametrize("layers", [(1,), (7,), (5, 3)])
def test_the_model_passes_the_checker_and_equals_the_torch_net(activation, layers):
    generator = torch.Generator().manual_seed(3)
    net = build(layers, activation, 2, 3, generator)
    x_mean, x_scale = np.array([0.5, -1.0]), np.array([2.0, 2.0])
    y_mean, y_scale = np.array([10.0, 20.0, -5.0]), np.array([3.0, 0.5, 7.0])
    model = _write(net, activation, x_mean, x_scale, y_mean, y_scale)
    onnx.checker.check_model(onnx.load_model_from_string(model), full_check=True)
    uv = np.random.default_rng(0).normal(size=(257, 2)) * 3
    with torch.no_grad():
        expected = net(torch.from_numpy((uv - x_mean) / x_scale)).numpy() * y_scale + y_mean
    np.testing.assert_allclose(OnnxSurfaceMap(model)(uv), expected, rtol=1e-12, atol=1e-9)


def test_an_averaged_net_is_written_like_any_other():
    generator = torch.Generator().manual_seed(0)
    nets = [build((4, 6), "tanh", 2, 3, generator) for _ in range(3)]
    mean = mean_of(*nets)
    zeros, ones = np.zeros(2), np.ones(2)
    surface = OnnxSurfaceMap(_write(mean, "tanh", zeros, ones, np.zeros(3), np.ones(3)))
    uv = np.random.default_rng(1).normal(size=(50, 2))
    with torch.no_grad():
        expected = sum(n(torch.from_numpy(uv)) for n in nets).numpy() / 3
    np.testing.assert_allclose(surface(uv), expected, atol=1e-12)
    assert surface(np.empty((0, 2))).shape == (0, 3)


def test_an_unknown_activation_is_refused():
    with pytest.raises(ValueError, match="no ONNX operator for activation 'gelu'"):
        mlp_model([(np.ones((2, 3)), np.zeros(3))], "gelu", np.zeros(2), np.ones(2),
                  np.zeros(3), np.ones(3))
