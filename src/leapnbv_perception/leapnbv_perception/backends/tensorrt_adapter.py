"""Every call into the `tensorrt` module: parse and build (with the FP16 precision plan), deserialize,
describe the engine's tensors, execute through either API.

`tensorrt` is imported only when a `TensorRTAdapter` is created (tests pass a fake module), so
this module imports on machines without it. Both APIs are handled: the TensorRT 8.5 binding API
(`execute_v2` on a list of device pointers) and the TensorRT 10 tensor API (`set_tensor_address`,
`execute_async_v3`).

FP16 precision plan (`precision_plan.py`): the named layers get `layer.precision = FP32`
and FP32 output types, and the builder flag OBEY_PRECISION_CONSTRAINTS makes TensorRT honour
them (TensorRT 8.5 and 10; 8.5 has no INormalizationLayer, so an ONNX LayerNorm arrives as
reduce/pow/sqrt layers, which is what the plan's patterns name). TensorRT 10's alternative,
a STRONGLY_TYPED network, takes the precisions from the ONNX's own types instead (export the
model with the FP32 islands as float32 and the rest float16, build without the FP16 flag);
per-layer precisions cannot be set on such a network, so this backend does not create one.
"""

from __future__ import annotations

import logging
import os
from collections import OrderedDict
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np

from leapnbv_perception.backends.base import BackendError, TensorSpec
from leapnbv_perception.backends.precision_plan import PrecisionPlan

# The TensorRT backend's one logger: its messages are configured and filtered under one name.
LOGGER = logging.getLogger("leapnbv_perception.backends.tensorrt_backend")

WORKSPACE_BYTES = 1 << 30


class TensorRTAdapter:
    """Every call into the tensorrt module: build, deserialize, describe, execute.

    Args:
        trt: the tensorrt module (injected by tests; imported lazily otherwise).

    Raises:
        BackendError: when tensorrt is not importable.
    """

    def __init__(self, trt: Any = None) -> None:
        if trt is None:
            try:
                import tensorrt

                trt = tensorrt
            except ImportError as error:
                raise BackendError(
                    "backend 'tensorrt' needs the TensorRT Python package (JetPack ships it as "
                    "python3-libnvinfer); use backend 'onnxruntime' on machines without it"
                ) from error
        self.trt = trt
        self.logger = trt.Logger(trt.Logger.WARNING)
        self._runtime = trt.Runtime(self.logger)

    @property
    def version(self) -> str:
        return str(getattr(self.trt, "__version__", "unknown"))

    def build_serialized(
        self, onnx_bytes: bytes, precision: str, source: str = "", plan: Optional[PrecisionPlan] = None
    ) -> Tuple[bytes, List[str], List[str]]:
        """Parse the ONNX model and build a serialized engine.

        Args:
            onnx_bytes: the model.
            precision: "fp32" or "fp16".
            source: the ONNX path, for messages.
            plan: FP16 precision plan (used for "fp16" only).

        Returns:
            (engine bytes, layers kept in FP32, layers the plan named but whose outputs are not
            floating point and so were left alone).

        Raises:
            BackendError: with the parser's errors, an entry of the plan that names no layer,
                or when the build fails.
        """
        trt = self.trt
        builder = trt.Builder(self.logger)
        flags = 0
        creation_flags = getattr(trt, "NetworkDefinitionCreationFlag", None)
        if creation_flags is not None and hasattr(creation_flags, "EXPLICIT_BATCH"):
            # Required by TensorRT 8.x, deprecated (ignored) by TensorRT 10.
            flags = 1 << int(creation_flags.EXPLICIT_BATCH)
        network = builder.create_network(flags)
        parser = trt.OnnxParser(network, self.logger)
        # With the file's path the parser finds weights stored outside the graph (external data).
        parsed = parser.parse(onnx_bytes, source) if source and os.path.isfile(source) else parser.parse(onnx_bytes)
        if not parsed:
            errors = [str(parser.get_error(index)) for index in range(parser.num_errors)]
            raise BackendError("TensorRT could not parse '%s': %s" % (source, "; ".join(errors)))
        config = builder.create_builder_config()
        if hasattr(config, "set_memory_pool_limit"):
            config.set_memory_pool_limit(trt.MemoryPoolType.WORKSPACE, WORKSPACE_BYTES)
        kept: List[str] = []
        skipped: List[str] = []
        if precision == "fp16":
            config.set_flag(trt.BuilderFlag.FP16)
            if plan is not None:
                kept, skipped = self.apply_precision_plan(network, config, plan, source)
        serialized = builder.build_serialized_network(network, config)
        if serialized is None:
            raise BackendError("TensorRT failed to build an engine from '%s' (%s)" % (source, precision))
        return bytes(serialized), kept, skipped

    def apply_precision_plan(
        self, network: Any, config: Any, plan: PrecisionPlan, source: str = ""
    ) -> Tuple[List[str], List[str]]:
        """Pin the plan's layers to FP32 (precision and output types) and make TensorRT obey.

        Returns:
            (layers kept in FP32, named layers skipped because an output is not floating point).

        Raises:
            BackendError: when an entry of the plan names no layer of the network.
        """
        trt = self.trt
        layers = [network.get_layer(index) for index in range(network.num_layers)]
        names = [layer.name for layer in layers]
        selected, unmatched = plan.select(names)
        if unmatched:
            raise BackendError(
                "precision plan '%s' does not fit '%s': %d entr%s name no layer: %s (the network's layers "
                "begin %s); was the plan made for another export?"
                % (plan.path, source, len(unmatched), "y" if len(unmatched) == 1 else "ies",
                   ", ".join(unmatched[:10]), ", ".join(names[:5]))
            )
        float_types = {trt.DataType.FLOAT, trt.DataType.HALF}
        wanted = set(selected)
        kept: List[str] = []
        skipped: List[str] = []
        for layer in layers:
            if layer.name not in wanted:
                continue
            outputs = [layer.get_output(index) for index in range(layer.num_outputs)]
            if not outputs or any(output.dtype not in float_types for output in outputs):
                skipped.append(layer.name)
                continue
            layer.precision = trt.float32
            for index in range(layer.num_outputs):
                layer.set_output_type(index, trt.float32)
            kept.append(layer.name)
        if kept:
            flag = getattr(trt.BuilderFlag, "OBEY_PRECISION_CONSTRAINTS", None)
            if flag is None:  # TensorRT < 8.2
                flag = trt.BuilderFlag.STRICT_TYPES
            config.set_flag(flag)
        return kept, skipped

    def deserialize(self, data: bytes) -> Any:
        """Deserialize an engine; None when TensorRT rejects the bytes."""
        try:
            return self._runtime.deserialize_cuda_engine(data)
        except (RuntimeError, TypeError, ValueError) as error:  # which one depends on the version
            LOGGER.warning("TensorRT could not deserialize the cached engine: %s", error)
            return None

    def uses_tensor_api(self, engine: Any) -> bool:
        """True for the name-based tensor API (TensorRT >= 8.5/10), False for bindings."""
        return hasattr(engine, "num_io_tensors") and hasattr(engine, "get_tensor_name")

    def describe(self, engine: Any) -> Tuple[Dict[str, TensorSpec], Dict[str, TensorSpec]]:
        """Inputs and outputs of an engine (name -> TensorSpec), through either API."""
        trt = self.trt
        inputs: Dict[str, TensorSpec] = OrderedDict()
        outputs: Dict[str, TensorSpec] = OrderedDict()
        if self.uses_tensor_api(engine):
            for index in range(engine.num_io_tensors):
                name = engine.get_tensor_name(index)
                spec = TensorSpec(
                    tuple(int(d) for d in engine.get_tensor_shape(name)),
                    np.dtype(trt.nptype(engine.get_tensor_dtype(name))).name,
                )
                is_input = engine.get_tensor_mode(name) == trt.TensorIOMode.INPUT
                (inputs if is_input else outputs)[name] = spec
        else:
            for index in range(engine.num_bindings):
                name = engine.get_binding_name(index)
                spec = TensorSpec(
                    tuple(int(d) for d in engine.get_binding_shape(index)),
                    np.dtype(trt.nptype(engine.get_binding_dtype(index))).name,
                )
                (inputs if engine.binding_is_input(index) else outputs)[name] = spec
        return inputs, outputs

    def create_context(self, engine: Any) -> Any:
        context = engine.create_execution_context()
        if context is None:
            raise BackendError("TensorRT could not create an execution context")
        return context

    def binding_order(self, engine: Any) -> List[str]:
        """Binding names by binding index (binding API)."""
        return [engine.get_binding_name(index) for index in range(engine.num_bindings)]

    def execute_bindings(self, context: Any, bindings: List[int]) -> None:
        """TensorRT 8.x: synchronous execution on a list of device pointers."""
        if not context.execute_v2(bindings):
            raise BackendError("TensorRT execute_v2 failed")

    def execute_tensors(self, context: Any, addresses: Mapping[str, int], stream_handle: int) -> None:
        """TensorRT 10: set each tensor's address, then enqueue on the stream."""
        for name, pointer in addresses.items():
            context.set_tensor_address(name, pointer)
        if not context.execute_async_v3(stream_handle):
            raise BackendError("TensorRT execute_async_v3 failed")
