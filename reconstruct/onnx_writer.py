"""Write a small MLP as an ONNX model: the protobuf encoded here, without the `onnx` package.

`torch.onnx.export` always imports the `onnx` package (to look for script functions), and with
it `ml_dtypes`: 0.6–1.3 s per process on this machine, paid by every process that fits a
surface, against a few milliseconds for the model itself. An MLP's graph is a short chain of
standard operators, so its ModelProto is written here directly (the wire format of
onnx.proto3: varints and length-delimited fields); tests check it with `onnx.checker` and
against the torch network's outputs.

Graph: ``xyz = mlp((uv - x_mean) / x_scale) * y_scale + y_mean`` in float64, each hidden
layer ``activation(h @ W + b)``, the output layer linear; input ``uv`` (n, d_in), output
``xyz`` (n, d_out), n dynamic.
"""

from __future__ import annotations

import numpy as np

OPSET = 17
IR_VERSION = 8  # the IR version of opset 17
_DOUBLE = 11  # TensorProto.DataType.DOUBLE
ACTIVATIONS = ("tanh", "sigmoid", "relu", "elu", "softplus")


def _varint(value: int) -> bytes:
    out = bytearray()
    value &= (1 << 64) - 1  # int64 as protobuf encodes it (two's complement)
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _int(field: int, value: int) -> bytes:
    return _varint(field << 3) + _varint(int(value))


def _bytes(field: int, payload: bytes | str) -> bytes:
    if isinstance(payload, str):
        payload = payload.encode()
    return _varint(field << 3 | 2) + _varint(len(payload)) + payload


def _tensor(name: str, array) -> bytes:
    """TensorProto: dims 1, data_type 2, name 8, raw_data 9 (little-endian float64)."""
    array = np.ascontiguousarray(array, dtype="<f8")
    return (b"".join(_int(1, d) for d in array.shape) + _int(2, _DOUBLE) + _bytes(8, name)
            + _bytes(9, array.tobytes()))


def _value_info(name: str, width: int) -> bytes:
    """ValueInfoProto of a (n, width) float64 tensor, n dynamic."""
    dims = _bytes(1, _bytes(2, "n")) + _bytes(1, _int(1, width))  # Dimension: dim_param, value
    tensor_type = _int(1, _DOUBLE) + _bytes(2, dims)
    return _bytes(1, name) + _bytes(2, _bytes(1, tensor_type))


def _node(op: str, inputs: list[str], output: str) -> bytes:
    """NodeProto: input 1, output 2, name 3, op_type 4."""
    return (b"".join(_bytes(1, i) for i in inputs) + _bytes(2, output) + _bytes(3, output)
            + _bytes(4, op))


def _activation(name: str, z: str, h: str) -> list[bytes]:
    """Nodes computing ``h = name(z)``. onnxruntime has no float64 Elu or Softplus kernel, so
    those are composed of kernels it has: elu(z) = relu(z) + exp(−relu(−z)) − 1 and
    softplus(z) = relu(z) + log(1 + exp(−|z|)) (stable for large |z|)."""
    if name in ("tanh", "sigmoid", "relu"):
        return [_node(name.capitalize(), [z], h)]
    if name == "elu":
        return [_node("Neg", [z], f"{h}_neg"), _node("Relu", [f"{h}_neg"], f"{h}_negpart"),
                _node("Neg", [f"{h}_negpart"], f"{h}_min"), _node("Exp", [f"{h}_min"], f"{h}_exp"),
                _node("Sub", [f"{h}_exp", "one"], f"{h}_tail"), _node("Relu", [z], f"{h}_pos"),
                _node("Add", [f"{h}_pos", f"{h}_tail"], h)]
    return [_node("Abs", [z], f"{h}_abs"), _node("Neg", [f"{h}_abs"], f"{h}_nabs"),
            _node("Exp", [f"{h}_nabs"], f"{h}_exp"), _node("Add", [f"{h}_exp", "one"], f"{h}_1p"),
            _node("Log", [f"{h}_1p"], f"{h}_log"), _node("Relu", [z], f"{h}_pos"),
            _node("Add", [f"{h}_pos", f"{h}_log"], h)]


def mlp_model(layers, activation: str, x_mean, x_scale, y_mean, y_scale) -> bytes:
    """ONNX bytes of the normalised MLP.

    layers : [(weight (in, out), bias (out,))], hidden layers then the linear output layer;
    activation : one of ``ACTIVATIONS``; x_mean, x_scale : (d_in,); y_mean, y_scale :
    (d_out,)."""
    if activation not in ACTIVATIONS:
        raise ValueError(f"no ONNX operator for activation {activation!r}")
    initializers = [_tensor("x_mean", x_mean), _tensor("x_scale", x_scale),
                    _tensor("y_mean", y_mean), _tensor("y_scale", y_scale),
                    _tensor("one", np.ones(1))]
    nodes = [_node("Sub", ["uv", "x_mean"], "centred"), _node("Div", ["centred", "x_scale"], "h0")]
    here = "h0"
    for index, (weight, bias) in enumerate(layers):
        initializers += [_tensor(f"w{index}", weight), _tensor(f"b{index}", bias)]
        nodes += [_node("MatMul", [here, f"w{index}"], f"m{index}"),
                  _node("Add", [f"m{index}", f"b{index}"], f"z{index}")]
        here = f"z{index}"
        if index < len(layers) - 1:
            nodes += _activation(activation, here, f"h{index + 1}")
            here = f"h{index + 1}"
    nodes += [_node("Mul", [here, "y_scale"], "scaled"), _node("Add", ["scaled", "y_mean"], "xyz")]
    d_in, d_out = len(np.ravel(x_mean)), len(np.ravel(y_mean))
    graph = (b"".join(_bytes(1, n) for n in nodes) + _bytes(2, "surface_map")
             + b"".join(_bytes(5, t) for t in initializers)
             + _bytes(11, _value_info("uv", d_in)) + _bytes(12, _value_info("xyz", d_out)))
    return (_int(1, IR_VERSION) + _bytes(2, "scanstation") + _bytes(7, graph)
            + _bytes(8, _bytes(1, "") + _int(2, OPSET)))
