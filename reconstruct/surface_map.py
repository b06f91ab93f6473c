"""The learned 2D → 3D surface map as an ONNX model, evaluated with onnxruntime (no torch).

The model carries its own input/output normalisation, so callers pass embedding coordinates and
get points in the cloud's units. Re-meshing only ever needs this object.
"""

from __future__ import annotations

import numpy as np
import onnxruntime

from .errors import InvalidInputError


def _session(model: bytes) -> onnxruntime.InferenceSession:
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    return onnxruntime.InferenceSession(model, options, providers=["CPUExecutionProvider"])


class OnnxSurfaceMap:
    """``surface_map(uv)`` : (n, 2) embedding coordinates → (n, 3) points, float64."""

    def __init__(self, model: bytes):
        self._model = bytes(model)
        try:
            self._session = _session(self._model)
        except Exception as exc:
            raise InvalidInputError(f"not a usable ONNX surface map ({exc})") from exc
        (inp,) = self._session.get_inputs()
        (out,) = self._session.get_outputs()
        self._input_name, self._output_name = inp.name, out.name
        self._dtype = np.float64 if "double" in inp.type else np.float32
        self.input_dim = int(inp.shape[1])
        self.output_dim = int(out.shape[1])

    @classmethod
    def from_bytes(cls, model: bytes) -> OnnxSurfaceMap:
        return cls(model)

    def to_bytes(self) -> bytes:
        """The serialised ONNX model (opens in any ONNX tool)."""
        return self._model

    def __call__(self, uv) -> np.ndarray:
        uv = np.asarray(uv, dtype=self._dtype)
        if uv.ndim != 2 or uv.shape[1] != self.input_dim:
            raise InvalidInputError(
                f"surface map takes (n, {self.input_dim}) coordinates, got shape {uv.shape}"
            )
        if len(uv) == 0:
            return np.empty((0, self.output_dim))
        (xyz,) = self._session.run([self._output_name], {self._input_name: uv})
        return xyz.astype(np.float64, copy=False)

    # Picklable (sklearn.clone, multiprocessing): the session is rebuilt from the bytes.
    def __getstate__(self):
        return {"model": self._model}

    def __setstate__(self, state):
        self.__init__(state["model"])

    def __repr__(self) -> str:
        return f"<OnnxSurfaceMap {self.input_dim}→{self.output_dim}, {len(self._model)} bytes>"
