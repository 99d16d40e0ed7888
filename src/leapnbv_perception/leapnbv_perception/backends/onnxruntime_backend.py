"""onnxruntime engine backend (CPU by default; other providers by parameter)."""

from __future__ import annotations

from collections import OrderedDict
from typing import Dict, Mapping, Optional, Sequence

import numpy as np

from leapnbv_perception.backends.base import (
    BackendError,
    EngineBackend,
    Tensor,
    TensorSpec,
    check_inputs,
    require_model_file,
)

# onnxruntime's type strings -> numpy dtype names.
_ORT_TYPES = {
    "tensor(float)": "float32",
    "tensor(float16)": "float16",
    "tensor(double)": "float64",
    "tensor(int64)": "int64",
    "tensor(int32)": "int32",
    "tensor(uint8)": "uint8",
    "tensor(bool)": "bool",
}


# Parameter value -> onnxruntime.GraphOptimizationLevel member.
GRAPH_OPTIMIZATIONS = {"disable": "ORT_DISABLE_ALL", "basic": "ORT_ENABLE_BASIC", "extended": "ORT_ENABLE_EXTENDED",
                       "all": "ORT_ENABLE_ALL"}


class OnnxRuntimeBackend(EngineBackend):
    """Runs an ONNX model with onnxruntime.

    Args:
        model_path: the ONNX file.
        providers: execution providers in priority order; default ["CPUExecutionProvider"].
        intra_op_threads: threads per operator (0 = onnxruntime's default).
        precision: reported precision; the model runs in the types it was exported with.
        graph_optimization: onnxruntime's graph optimization level: one of GRAPH_OPTIMIZATIONS.
        parallel_execution: run independent branches of the graph in parallel (inter_op_threads
            threads) instead of one operator after the other.
        inter_op_threads: threads for parallel execution (0 = onnxruntime's default).
        thread_spinning: idle worker threads spin waiting for work (onnxruntime's default); False makes them
            sleep (session.intra_op / inter_op.allow_spinning = 0), so they take no CPU from other processes.

    Raises:
        ModelFileNotFoundError: when model_path does not exist.
        BackendError: when onnxruntime cannot load the model.
    """

    def __init__(
        self,
        model_path: str,
        providers: Optional[Sequence[str]] = None,
        intra_op_threads: int = 0,
        precision: str = "fp32",
        graph_optimization: str = "all",
        parallel_execution: bool = False,
        inter_op_threads: int = 1,
        thread_spinning: bool = True,
    ) -> None:
        import onnxruntime

        self.model_path = require_model_file(model_path)
        if graph_optimization not in GRAPH_OPTIMIZATIONS:
            raise ValueError("graph_optimization '%s' is not one of %s" % (graph_optimization, GRAPH_OPTIMIZATIONS))
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = int(intra_op_threads)
        options.inter_op_num_threads = int(inter_op_threads)
        options.execution_mode = (onnxruntime.ExecutionMode.ORT_PARALLEL if parallel_execution
                                  else onnxruntime.ExecutionMode.ORT_SEQUENTIAL)
        options.graph_optimization_level = getattr(onnxruntime.GraphOptimizationLevel,
                                                   GRAPH_OPTIMIZATIONS[graph_optimization])
        if not thread_spinning:
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
            options.add_session_config_entry("session.inter_op.allow_spinning", "0")
        self._providers = list(providers) if providers else ["CPUExecutionProvider"]
        try:
            self._session = onnxruntime.InferenceSession(
                self.model_path, sess_options=options, providers=self._providers
            )
        except Exception as error:  # onnxruntime raises its own untyped exceptions
            raise BackendError("onnxruntime could not load '%s': %s" % (self.model_path, error)) from error
        self._inputs = OrderedDict(
            (arg.name, TensorSpec(tuple(arg.shape), _ORT_TYPES.get(arg.type, arg.type)))
            for arg in self._session.get_inputs()
        )
        self._outputs = OrderedDict(
            (arg.name, TensorSpec(tuple(arg.shape), _ORT_TYPES.get(arg.type, arg.type)))
            for arg in self._session.get_outputs()
        )
        self._output_names = list(self._outputs)
        self._precision = precision

    @property
    def providers(self) -> Sequence[str]:
        """Providers the session actually uses."""
        return list(self._session.get_providers())

    def run(self, inputs: Mapping[str, Tensor]) -> Dict[str, Tensor]:
        check_inputs(inputs, self._inputs, self.model_path)
        feed = {
            name: np.ascontiguousarray(inputs[name], dtype=spec.dtype) for name, spec in self._inputs.items()
        }
        try:
            values = self._session.run(self._output_names, feed)
        except Exception as error:
            raise BackendError("onnxruntime failed on '%s': %s" % (self.model_path, error)) from error
        return dict(zip(self._output_names, values))


def nudge_last_bit(values: Tensor) -> Tensor:
    """Floating-point ``values`` moved by one unit in the last place, away from zero.

    Zeros become the smallest positive subnormal; arrays of other types are returned unchanged.
    """
    if not np.issubdtype(values.dtype, np.floating):
        return values
    return np.nextafter(values, np.where(np.signbit(values), -np.inf, np.inf).astype(values.dtype))


class LastBitNudgedOnnxRuntimeBackend(OnnxRuntimeBackend):
    """Tests only: an OnnxRuntimeBackend whose every floating-point output is moved by one ulp (nudge_last_bit).

    The regression's numeric-configuration test runs the graph with it (engine backend
    ``onnxruntime_last_bit_nudged``) to show that a difference in the engines' last bit, as another CPU's kernels
    give, is not reported as a change. Never a default: a robot has no use for it.
    """

    def run(self, inputs: Mapping[str, Tensor]) -> Dict[str, Tensor]:
        return {name: nudge_last_bit(np.asarray(value)) for name, value in super().run(inputs).items()}
