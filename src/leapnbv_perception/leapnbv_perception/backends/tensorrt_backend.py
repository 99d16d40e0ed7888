"""TensorRT engine backend: builds an engine from the ONNX file on the device and caches it.

Every call into `tensorrt` sits in `TensorRTAdapter` and every CUDA memory call in
`CudaMemory`; the rest (cache key, cache path, rebuild-on-failure, choice between the
TensorRT 8.5 binding API and the TensorRT 10 tensor API, input/output bookkeeping) is plain
Python that the tests exercise with a fake `tensorrt` module and fake device memory.

CUDA memory: `cuda-python` is tried first (`cuda.bindings.runtime`, or the older
`cuda.cudart`), then `pycuda` (JetPack 5 images usually ship pycuda). Neither, nor
`tensorrt`, is imported before a TensorRT backend is actually created, so this module
imports on machines without them.

Engine cache: `<cache_dir>/<onnx stem>.<precision>.<key[:20]>.engine`, where key =
sha256(sha256(ONNX bytes) | TensorRT version | GPU name | precision). The default cache_dir
is `$LEAPNBV_ENGINE_CACHE`, else `~/.cache/leapnbv/tensorrt`. A cached engine that fails to
deserialize (TensorRT upgrade, truncated file) is rebuilt and overwritten.
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections import OrderedDict
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np

from leapnbv_common.atomic_files import write_bytes_atomically
from leapnbv_perception.backends.base import (
    BackendError,
    EngineBackend,
    TensorSpec,
    check_inputs,
    normalize_precision,
    require_model_file,
)

LOGGER = logging.getLogger(__name__)

ENGINE_CACHE_ENV = "LEAPNBV_ENGINE_CACHE"
WORKSPACE_BYTES = 1 << 30


# ----------------------------------------------------------------------------------------
# Cache key and path (pure functions)
# ----------------------------------------------------------------------------------------


def engine_cache_key(onnx_bytes: bytes, trt_version: str, gpu_name: str, precision: str) -> str:
    """Key of a built engine: it is valid only for this ONNX, TensorRT, GPU and precision.

    Args:
        onnx_bytes: the ONNX file's content.
        trt_version: tensorrt.__version__.
        gpu_name: CUDA device name, e.g. "Xavier".
        precision: "fp32" or "fp16".

    Returns:
        64 hex characters.
    """
    onnx_digest = hashlib.sha256(onnx_bytes).hexdigest()
    text = "|".join([onnx_digest, str(trt_version), str(gpu_name).strip(), normalize_precision(precision)])
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def default_engine_cache_dir() -> str:
    """$LEAPNBV_ENGINE_CACHE, else ~/.cache/leapnbv/tensorrt."""
    configured = os.environ.get(ENGINE_CACHE_ENV, "").strip()
    if configured:
        return configured
    return os.path.join(os.path.expanduser("~"), ".cache", "leapnbv", "tensorrt")


def engine_cache_path(cache_dir: Optional[str], onnx_path: str, precision: str, key: str) -> str:
    """File the engine for `key` is cached in.

    Args:
        cache_dir: folder; None for `default_engine_cache_dir()`.
        onnx_path: the ONNX file (its stem names the engine for humans).
        precision: "fp32" or "fp16".
        key: `engine_cache_key(...)`.

    Returns:
        `<cache_dir>/<onnx stem>.<precision>.<key[:20]>.engine`.
    """
    folder = cache_dir if cache_dir else default_engine_cache_dir()
    stem = os.path.splitext(os.path.basename(onnx_path))[0]
    return os.path.join(folder, "%s.%s.%s.engine" % (stem, normalize_precision(precision), key[:20]))


# ----------------------------------------------------------------------------------------
# Thin adapters: the only code that touches tensorrt and CUDA
# ----------------------------------------------------------------------------------------


class CudaMemory:
    """Device buffers, copies and one stream, through cuda-python or pycuda.

    Args:
        device: CUDA device index.

    Raises:
        BackendError: when neither cuda-python nor pycuda can be imported.
    """

    def __init__(self, device: int = 0) -> None:
        self._allocations: Dict[int, Any] = {}
        self._cudart = None
        self._pycuda = None
        try:
            try:
                from cuda.bindings import runtime as cudart  # cuda-python >= 12.6
            except ImportError:
                from cuda import cudart  # older cuda-python
            self._cudart = cudart
            self._check(cudart.cudaSetDevice(device))
            self._stream = self._check(cudart.cudaStreamCreate())
            self._device = device
            return
        except ImportError:
            pass
        try:
            import pycuda.driver as driver

            driver.init()
            self._context = driver.Device(device).retain_primary_context()
            self._context.push()
            self._pycuda = driver
            self._stream_object = driver.Stream()
            self._stream = self._stream_object.handle
            self._device = device
        except ImportError as error:
            raise BackendError(
                "the TensorRT backend needs cuda-python ('pip install cuda-python') or pycuda "
                "for device memory; neither is importable"
            ) from error

    def _check(self, result: Any) -> Any:
        """Unpack cuda-python's (error, value...) tuples, raising on an error code."""
        if not isinstance(result, tuple):
            result = (result,)
        error = result[0]
        if int(error) != 0:
            raise BackendError("CUDA runtime call failed: %s" % (error,))
        if len(result) == 1:
            return None
        return result[1] if len(result) == 2 else result[1:]

    @property
    def stream_handle(self) -> int:
        """Raw cudaStream_t as an int (what execute_async_v3 takes)."""
        return int(self._stream)

    def gpu_name(self) -> str:
        """Name of the device, part of the engine cache key."""
        if self._cudart is not None:
            properties = self._check(self._cudart.cudaGetDeviceProperties(self._device))
            name = properties.name
            return name.decode("utf-8", "replace").rstrip("\x00") if isinstance(name, bytes) else str(name)
        return str(self._pycuda.Device(self._device).name())

    def allocate(self, nbytes: int) -> int:
        """Allocate device memory; returns its address."""
        nbytes = max(int(nbytes), 1)
        if self._cudart is not None:
            pointer = int(self._check(self._cudart.cudaMalloc(nbytes)))
            self._allocations[pointer] = pointer
            return pointer
        allocation = self._pycuda.mem_alloc(nbytes)
        self._allocations[int(allocation)] = allocation
        return int(allocation)

    def copy_to_device(self, pointer: int, host: np.ndarray) -> None:
        """Copy a contiguous host array to device memory (synchronous)."""
        host = np.ascontiguousarray(host)
        if self._cudart is not None:
            kind = self._cudart.cudaMemcpyKind.cudaMemcpyHostToDevice
            self._check(self._cudart.cudaMemcpy(pointer, host.ctypes.data, host.nbytes, kind))
        else:
            self._pycuda.memcpy_htod(self._allocations[pointer], host)

    def copy_to_host(self, host: np.ndarray, pointer: int) -> None:
        """Copy device memory into a contiguous host array (synchronous)."""
        if self._cudart is not None:
            kind = self._cudart.cudaMemcpyKind.cudaMemcpyDeviceToHost
            self._check(self._cudart.cudaMemcpy(host.ctypes.data, pointer, host.nbytes, kind))
        else:
            self._pycuda.memcpy_dtoh(host, self._allocations[pointer])

    def synchronize(self) -> None:
        """Wait for the stream."""
        if self._cudart is not None:
            self._check(self._cudart.cudaStreamSynchronize(self._stream))
        else:
            self._stream_object.synchronize()

    def free_all(self) -> None:
        """Release every allocation."""
        for pointer, allocation in list(self._allocations.items()):
            if self._cudart is not None:
                self._cudart.cudaFree(pointer)
            else:
                allocation.free()
        self._allocations.clear()


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
                import tensorrt as trt
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

    def build_serialized(self, onnx_bytes: bytes, precision: str, source: str = "") -> bytes:
        """Parse the ONNX model and build a serialized engine.

        Raises:
            BackendError: with the parser's errors, or when the build fails.
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
        if not parser.parse(onnx_bytes):
            errors = [str(parser.get_error(index)) for index in range(parser.num_errors)]
            raise BackendError("TensorRT could not parse '%s': %s" % (source, "; ".join(errors)))
        config = builder.create_builder_config()
        if hasattr(config, "set_memory_pool_limit"):
            config.set_memory_pool_limit(trt.MemoryPoolType.WORKSPACE, WORKSPACE_BYTES)
        if precision == "fp16":
            config.set_flag(trt.BuilderFlag.FP16)
        serialized = builder.build_serialized_network(network, config)
        if serialized is None:
            raise BackendError("TensorRT failed to build an engine from '%s' (%s)" % (source, precision))
        return bytes(serialized)

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


# ----------------------------------------------------------------------------------------
# Cache logic and the backend
# ----------------------------------------------------------------------------------------


def load_or_build_engine(
    adapter: TensorRTAdapter,
    onnx_path: str,
    precision: str,
    gpu_name: str,
    cache_dir: Optional[str] = None,
) -> Tuple[Any, str, bool]:
    """Deserialize the cached engine for this ONNX/TensorRT/GPU/precision, or build it.

    Args:
        adapter: the TensorRT adapter.
        onnx_path: the ONNX file.
        precision: "fp32" or "fp16".
        gpu_name: device name (part of the key).
        cache_dir: engine cache folder (None: default).

    Returns:
        (engine, cache file path, True when the engine was built now).

    Raises:
        ModelFileNotFoundError: when onnx_path does not exist.
        BackendError: when building fails or the fresh engine does not deserialize.
    """
    require_model_file(onnx_path)
    with open(onnx_path, "rb") as stream:
        onnx_bytes = stream.read()
    key = engine_cache_key(onnx_bytes, adapter.version, gpu_name, precision)
    path = engine_cache_path(cache_dir, onnx_path, precision, key)
    if os.path.isfile(path):
        with open(path, "rb") as stream:
            engine = adapter.deserialize(stream.read())
        if engine is not None:
            return engine, path, False
        LOGGER.warning("cached TensorRT engine '%s' is unusable; rebuilding from '%s'", path, onnx_path)
    LOGGER.info("building TensorRT %s engine from '%s' (this takes minutes on a Jetson)", precision, onnx_path)
    serialized = adapter.build_serialized(onnx_bytes, precision, onnx_path)
    write_bytes_atomically(path, serialized)
    engine = adapter.deserialize(serialized)
    if engine is None:
        raise BackendError("TensorRT could not deserialize the engine it just built from '%s'" % onnx_path)
    return engine, path, True


class TensorRTBackend(EngineBackend):
    """Runs an ONNX model through a cached TensorRT engine.

    Args:
        model_path: the ONNX file.
        precision: "fp32" or "fp16".
        engine_cache_dir: engine cache folder (None: `default_engine_cache_dir()`).
        trt: tensorrt module to use (tests inject a fake); None imports tensorrt.
        memory: device memory adapter (tests inject a fake); None creates `CudaMemory()`.

    Raises:
        ModelFileNotFoundError: when model_path does not exist.
        BackendError: when TensorRT or CUDA is unavailable or the engine cannot be built.
    """

    def __init__(
        self,
        model_path: str,
        precision: str = "fp32",
        engine_cache_dir: Optional[str] = None,
        trt: Any = None,
        memory: Any = None,
    ) -> None:
        self.model_path = require_model_file(model_path)
        self._precision = normalize_precision(precision)
        self._adapter = TensorRTAdapter(trt)
        self._memory = memory if memory is not None else CudaMemory()
        self._engine, self.engine_path, self.engine_was_built = load_or_build_engine(
            self._adapter, self.model_path, self._precision, self._memory.gpu_name(), engine_cache_dir
        )
        self._inputs, self._outputs = self._adapter.describe(self._engine)
        self._context = self._adapter.create_context(self._engine)
        self._tensor_api = self._adapter.uses_tensor_api(self._engine)
        self._host_outputs: Dict[str, np.ndarray] = {}
        self._device: Dict[str, int] = {}
        for name, spec in list(self._inputs.items()) + list(self._outputs.items()):
            if any(not isinstance(dim, int) or dim < 0 for dim in spec.shape):
                raise BackendError(
                    "engine from '%s' has a dynamic shape for '%s' %s; export with static shapes"
                    % (self.model_path, name, spec.shape)
                )
            nbytes = int(np.prod(spec.shape)) * np.dtype(spec.dtype).itemsize
            self._device[name] = self._memory.allocate(nbytes)
        for name, spec in self._outputs.items():
            self._host_outputs[name] = np.empty(spec.shape, dtype=spec.dtype)
        if not self._tensor_api:
            self._bindings = [self._device[name] for name in self._adapter.binding_order(self._engine)]

    @property
    def uses_tensor_api(self) -> bool:
        """True when the engine runs through the TensorRT 10 tensor API."""
        return self._tensor_api

    def run(self, inputs: Mapping[str, np.ndarray]) -> Dict[str, np.ndarray]:
        check_inputs(inputs, self._inputs, self.model_path)
        for name, spec in self._inputs.items():
            self._memory.copy_to_device(self._device[name], np.ascontiguousarray(inputs[name], dtype=spec.dtype))
        if self._tensor_api:
            self._adapter.execute_tensors(self._context, self._device, self._memory.stream_handle)
        else:
            self._adapter.execute_bindings(self._context, self._bindings)
        self._memory.synchronize()
        results = {}
        for name, host in self._host_outputs.items():
            self._memory.copy_to_host(host, self._device[name])
            results[name] = host.copy()
        return results

    def close(self) -> None:
        """Free device buffers."""
        self._memory.free_all()
