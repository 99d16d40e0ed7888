"""TensorRT engine backend: builds an engine from the ONNX file on the device and caches it.

Every call into `tensorrt` sits in `TensorRTAdapter` and every CUDA memory call in the
`CudaMemory` implementations; the rest (cache key, cache path, rebuild-on-failure, the FP16
precision plan, choice between the TensorRT 8.5 binding API and the TensorRT 10 tensor API,
input/output bookkeeping) is plain Python that the tests exercise with a fake `tensorrt`
module and fake CUDA libraries.

CUDA memory: `cuda-python` is tried first (`cuda.bindings.runtime`, or the older
`cuda.cudart`); when it is missing, or its first calls fail (a cuda-python built for CUDA 12
on JetPack 5's CUDA 11.4 driver answers cudaErrorInsufficientDriver, or a function its
driver lacks), the reason is logged and `pycuda` is used instead. Only when both fail does
the backend fail, naming both reasons. Neither library, nor `tensorrt`, is imported before a
TensorRT backend is actually created, so this module imports on machines without them.

Engine cache: `<cache_dir>/<onnx stem>.<precision>.<key[:20]>.engine`, where key =
sha256(sha256(ONNX bytes) | TensorRT version | GPU name | precision [| precision plan
digest, FP16 only]). The default cache_dir is `$LEAPNBV_ENGINE_CACHE`, else
`~/.cache/leapnbv/tensorrt`. A cached engine that fails to deserialize (TensorRT upgrade,
truncated file) is rebuilt and overwritten. Beside each engine, `<engine>.layers.json`
records the layers the precision plan kept in FP32, so a cache hit logs the same list.

FP16 precision plan (`precision_plan.py`): the named layers get `layer.precision = FP32`
and FP32 output types, and the builder flag OBEY_PRECISION_CONSTRAINTS makes TensorRT honour
them (TensorRT 8.5 and 10; 8.5 has no INormalizationLayer, so an ONNX LayerNorm arrives as
reduce/pow/sqrt layers, which is what the plan's patterns name). TensorRT 10's alternative,
a STRONGLY_TYPED network, takes the precisions from the ONNX's own types instead (export the
model with the FP32 islands as float32 and the rest float16, build without the FP16 flag);
per-layer precisions cannot be set on such a network, so this backend does not create one.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections import OrderedDict
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

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
from leapnbv_perception.backends.precision_plan import PrecisionPlan, PrecisionPlanError, load_precision_plan

LOGGER = logging.getLogger(__name__)

ENGINE_CACHE_ENV = "LEAPNBV_ENGINE_CACHE"
WORKSPACE_BYTES = 1 << 30


# ----------------------------------------------------------------------------------------
# Cache key and path (pure functions)
# ----------------------------------------------------------------------------------------


def external_data_digests(onnx_path: str) -> List[str]:
    """sha256 of each file the ONNX graph keeps tensors in (external data: a graph over 2 GiB keeps
    its weights in ``<model>.onnx.data``), in the order the graph names them; [] when it has none.

    The graph's own bytes do not change when only those files do, so the engine cache key needs them.
    """
    names = [os.path.basename(onnx_path) + ".data"] if os.path.isfile(onnx_path + ".data") else []
    try:
        import onnx

        proto = onnx.load(onnx_path, load_external_data=False)
    except Exception:  # noqa: BLE001 - no onnx, or a graph it cannot read (the parser reports that):
        pass  # the project's export convention, <model>.onnx.data beside it
    else:
        names = []
        for tensor in proto.graph.initializer:
            if tensor.data_location == onnx.TensorProto.EXTERNAL:
                location = next(entry.value for entry in tensor.external_data if entry.key == "location")
                if location not in names:
                    names.append(location)
    digests = []
    for name in names:
        path = os.path.join(os.path.dirname(os.path.abspath(onnx_path)), name)
        require_model_file(path)
        digest = hashlib.sha256()
        with open(path, "rb") as stream:
            for block in iter(lambda: stream.read(1 << 22), b""):
                digest.update(block)
        digests.append(name + ":" + digest.hexdigest())
    return digests


def engine_cache_key(
    onnx_bytes: bytes, trt_version: str, gpu_name: str, precision: str, plan_digest: str = "",
    external_digests: Sequence[str] = (),
) -> str:
    """Key of a built engine: it is valid only for this ONNX, TensorRT, GPU, precision and plan.

    Args:
        onnx_bytes: the ONNX file's content.
        trt_version: tensorrt.__version__.
        gpu_name: CUDA device name, e.g. "Xavier".
        precision: "fp32" or "fp16".
        plan_digest: `PrecisionPlan.digest` of the FP16 precision plan the engine is built
            with; "" for none (the key is then the same as without a plan).
        external_digests: `external_data_digests` of the model (its weights stored outside the
            graph); empty for none (the key is then the same as before).

    Returns:
        64 hex characters.
    """
    onnx_digest = hashlib.sha256(onnx_bytes).hexdigest()
    parts = [onnx_digest, str(trt_version), str(gpu_name).strip(), normalize_precision(precision)]
    if plan_digest:
        parts.append("plan:" + plan_digest)
    parts.extend("data:" + digest for digest in external_digests)
    return hashlib.sha256("|".join(parts).encode("utf-8")).hexdigest()


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


# cudaError_t values that mean "this cuda-python does not fit this driver" (CUDA runtime API).
CUDA_DRIVER_ERRORS = {
    3: "cudaErrorInitializationError",
    34: "cudaErrorStubLibrary",
    35: "cudaErrorInsufficientDriver",
    36: "cudaErrorCallRequiresNewerDriver",
    100: "cudaErrorNoDevice",
    803: "cudaErrorSystemDriverMismatch",
    804: "cudaErrorCompatNotSupportedOnDevice",
}


class CudaUnavailable(RuntimeError):
    """A CUDA library cannot be imported or does not work with this driver (try the next)."""


def _import_cudart() -> Any:
    try:
        from cuda.bindings import runtime as cudart  # cuda-python >= 12.6
    except ImportError:
        from cuda import cudart  # cuda-python 11.x .. 12.5
    return cudart


def _import_pycuda() -> Any:
    import pycuda.driver as driver

    return driver


def _error_text(error: Any) -> str:
    code = int(error)
    name = CUDA_DRIVER_ERRORS.get(code) or getattr(error, "name", "") or str(error)
    return "%s (%d)" % (name, code)


class CudaPythonMemory:
    """Device buffers, copies and one stream through cuda-python's runtime API.

    Args:
        device: CUDA device index.
        cudart: the runtime module (tests inject a fake); None imports it.

    Raises:
        CudaUnavailable: when cuda-python is missing or its first calls fail: the import, setting
            the device, creating the stream, reading the device name, a 16-byte malloc/free
            (these are where a CUDA 12 cuda-python on a CUDA 11.4 driver fails).
    """

    library = "cuda-python"

    def __init__(self, device: int = 0, cudart: Any = None) -> None:
        try:
            self._cudart = cudart if cudart is not None else _import_cudart()
        except Exception as error:  # noqa: BLE001 - ImportError, or a loader error raised at import
            raise CudaUnavailable("cuda-python is not importable (%s: %s)" % (type(error).__name__, error)) from error
        self._device = device
        self._allocations: Dict[int, int] = {}
        try:
            self._check(self._cudart.cudaSetDevice(device), "cudaSetDevice", probe=True)
            self._stream = self._check(self._cudart.cudaStreamCreate(), "cudaStreamCreate", probe=True)
            self._name = self._read_name()
            pointer = int(self._check(self._cudart.cudaMalloc(16), "cudaMalloc", probe=True))
            self._check(self._cudart.cudaFree(pointer), "cudaFree", probe=True)
        except CudaUnavailable:
            raise
        except Exception as error:  # noqa: BLE001 - cuda-python raises RuntimeError for a missing driver function
            raise CudaUnavailable(
                "cuda-python failed on this driver: %s: %s" % (type(error).__name__, error)
            ) from error

    def _check(self, result: Any, call: str = "CUDA runtime call", probe: bool = False) -> Any:
        """Unpack cuda-python's (error, value...) tuples, raising on an error code."""
        if not isinstance(result, tuple):
            result = (result,)
        error = result[0]
        if int(error) != 0:
            message = "%s failed: %s" % (call, _error_text(error))
            if probe:
                raise CudaUnavailable("cuda-python does not work here: " + message)
            raise BackendError("CUDA " + message)
        if len(result) == 1:
            return None
        return result[1] if len(result) == 2 else result[1:]

    def _read_name(self) -> str:
        properties = self._check(self._cudart.cudaGetDeviceProperties(self._device), "cudaGetDeviceProperties",
                                 probe=True)
        name = properties.name
        return name.decode("utf-8", "replace").rstrip("\x00") if isinstance(name, bytes) else str(name)

    @property
    def stream_handle(self) -> int:
        return int(self._stream)

    def gpu_name(self) -> str:
        return self._name

    def allocate(self, nbytes: int) -> int:
        pointer = int(self._check(self._cudart.cudaMalloc(max(int(nbytes), 1)), "cudaMalloc"))
        self._allocations[pointer] = pointer
        return pointer

    def copy_to_device(self, pointer: int, host: np.ndarray) -> None:
        host = np.ascontiguousarray(host)
        kind = self._cudart.cudaMemcpyKind.cudaMemcpyHostToDevice
        self._check(self._cudart.cudaMemcpy(pointer, host.ctypes.data, host.nbytes, kind), "cudaMemcpy")

    def copy_to_host(self, host: np.ndarray, pointer: int) -> None:
        kind = self._cudart.cudaMemcpyKind.cudaMemcpyDeviceToHost
        self._check(self._cudart.cudaMemcpy(host.ctypes.data, pointer, host.nbytes, kind), "cudaMemcpy")

    def synchronize(self) -> None:
        self._check(self._cudart.cudaStreamSynchronize(self._stream), "cudaStreamSynchronize")

    def free_all(self) -> None:
        for pointer in list(self._allocations):
            self._cudart.cudaFree(pointer)
        self._allocations.clear()


class PyCudaMemory:
    """Device buffers, copies and one stream through pycuda (its primary context).

    Args:
        device: CUDA device index.
        driver: `pycuda.driver` (tests inject a fake); None imports it.

    Raises:
        CudaUnavailable: when pycuda is missing or cannot initialise the device.
    """

    library = "pycuda"

    def __init__(self, device: int = 0, driver: Any = None) -> None:
        try:
            self._driver = driver if driver is not None else _import_pycuda()
        except Exception as error:  # noqa: BLE001 - ImportError (e.g. no libcuda.so.1), or its own errors
            raise CudaUnavailable("pycuda is not importable (%s: %s)" % (type(error).__name__, error)) from error
        self._device = device
        self._allocations: Dict[int, Any] = {}
        try:
            self._driver.init()
            self._context = self._driver.Device(device).retain_primary_context()
            self._context.push()
            self._stream_object = self._driver.Stream()
            self._name = str(self._driver.Device(device).name())
        except Exception as error:  # noqa: BLE001 - pycuda raises its own LogicError/RuntimeError
            raise CudaUnavailable("pycuda failed to initialise device %d: %s: %s"
                                  % (device, type(error).__name__, error)) from error

    @property
    def stream_handle(self) -> int:
        return int(self._stream_object.handle)

    def gpu_name(self) -> str:
        return self._name

    def allocate(self, nbytes: int) -> int:
        allocation = self._driver.mem_alloc(max(int(nbytes), 1))
        self._allocations[int(allocation)] = allocation
        return int(allocation)

    def copy_to_device(self, pointer: int, host: np.ndarray) -> None:
        self._driver.memcpy_htod(self._allocations[pointer], np.ascontiguousarray(host))

    def copy_to_host(self, host: np.ndarray, pointer: int) -> None:
        self._driver.memcpy_dtoh(host, self._allocations[pointer])

    def synchronize(self) -> None:
        self._stream_object.synchronize()

    def free_all(self) -> None:
        for allocation in list(self._allocations.values()):
            allocation.free()
        self._allocations.clear()


CUDA_MEMORY_LIBRARIES = (CudaPythonMemory, PyCudaMemory)


def CudaMemory(device: int = 0) -> Any:  # noqa: N802 - kept as the class-like factory it replaced
    """Device memory through the first CUDA library that works here: cuda-python, else pycuda.

    Each failure is logged as a warning with its reason (a version mismatch names the CUDA
    error); the returned object has `library` set to the one in use.

    Raises:
        BackendError: when no library works, with every library's reason.
    """
    reasons = []
    for implementation in CUDA_MEMORY_LIBRARIES:
        try:
            memory = implementation(device)
        except CudaUnavailable as error:
            reasons.append(str(error))
            LOGGER.warning("CUDA memory through %s is not usable, trying the next library: %s",
                           implementation.library, error)
            continue
        if reasons:
            LOGGER.warning("TensorRT backend uses %s for device memory (%s)", memory.library, "; ".join(reasons))
        return memory
    raise BackendError(
        "the TensorRT backend needs cuda-python (matching the driver's CUDA: cuda-python 11.x on JetPack 5) "
        "or pycuda for device memory; none works here: " + "; ".join(reasons)
    )


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


# ----------------------------------------------------------------------------------------
# Cache logic and the backend
# ----------------------------------------------------------------------------------------


def _plan_record_path(engine_path: str) -> str:
    return engine_path + ".layers.json"


def _log_kept_layers(engine_path: str, onnx_path: str, plan: PrecisionPlan, kept: List[str],
                     skipped: List[str], cached: bool) -> None:
    LOGGER.info(
        "TensorRT fp16 engine '%s' (%s '%s'): precision plan '%s' keeps %d layer%s in FP32: %s%s",
        engine_path, "cached, built from" if cached else "built from", onnx_path, plan.path, len(kept),
        "" if len(kept) == 1 else "s", ", ".join(kept) if kept else "(none)",
        "; skipped (outputs not floating point): %s" % ", ".join(skipped) if skipped else "",
    )


def load_or_build_engine(
    adapter: TensorRTAdapter,
    onnx_path: str,
    precision: str,
    gpu_name: str,
    cache_dir: Optional[str] = None,
    plan: Optional[PrecisionPlan] = None,
) -> Tuple[Any, str, bool, Optional[List[str]]]:
    """Deserialize the cached engine for this ONNX/TensorRT/GPU/precision/plan, or build it.

    Args:
        adapter: the TensorRT adapter.
        onnx_path: the ONNX file.
        precision: "fp32" or "fp16".
        gpu_name: device name (part of the key).
        cache_dir: engine cache folder (None: default).
        plan: FP16 precision plan; ignored (and logged so) for an fp32 engine.

    Returns:
        (engine, cache file path, True when the engine was built now, the layers the plan kept
        in FP32: None without a plan, or for a cached engine whose record file is missing).

    Raises:
        ModelFileNotFoundError: when onnx_path does not exist.
        BackendError: when building fails or the fresh engine does not deserialize.
    """
    require_model_file(onnx_path)
    with open(onnx_path, "rb") as stream:
        onnx_bytes = stream.read()
    if plan is not None and precision != "fp16":
        LOGGER.info("precision plan '%s' not used: the %s engine of '%s' runs every layer in FP32",
                    plan.path, precision, onnx_path)
        plan = None
    if plan is not None and plan.model_sha256 and plan.model_sha256 != hashlib.sha256(onnx_bytes).hexdigest():
        LOGGER.warning("precision plan '%s' was made for another ONNX (model_sha256 %s...), not '%s'",
                       plan.path, plan.model_sha256[:12], onnx_path)
    key = engine_cache_key(onnx_bytes, adapter.version, gpu_name, precision, plan.digest if plan else "",
                           external_data_digests(onnx_path))
    path = engine_cache_path(cache_dir, onnx_path, precision, key)
    if os.path.isfile(path):
        with open(path, "rb") as stream:
            engine = adapter.deserialize(stream.read())
        if engine is not None:
            kept = None
            if plan is not None:
                kept, skipped = _read_plan_record(path)
                if kept is None:
                    LOGGER.info("cached TensorRT engine '%s' was built with precision plan '%s' (its list of FP32 "
                                "layers is missing)", path, plan.path)
                else:
                    _log_kept_layers(path, onnx_path, plan, kept, skipped, cached=True)
            return engine, path, False, kept
        LOGGER.warning("cached TensorRT engine '%s' is unusable; rebuilding from '%s'", path, onnx_path)
    LOGGER.info("building TensorRT %s engine from '%s' (this takes minutes on a Jetson)", precision, onnx_path)
    serialized, kept, skipped = adapter.build_serialized(onnx_bytes, precision, onnx_path, plan)
    write_bytes_atomically(path, serialized)
    if plan is not None:
        record = {"precision_plan": plan.path, "plan_digest": plan.digest, "kept_fp32": kept, "skipped": skipped}
        write_bytes_atomically(_plan_record_path(path), (json.dumps(record, indent=1) + "\n").encode("utf-8"))
        _log_kept_layers(path, onnx_path, plan, kept, skipped, cached=False)
    engine = adapter.deserialize(serialized)
    if engine is None:
        raise BackendError("TensorRT could not deserialize the engine it just built from '%s'" % onnx_path)
    return engine, path, True, (kept if plan is not None else None)


def _read_plan_record(engine_path: str) -> Tuple[Optional[List[str]], List[str]]:
    try:
        with open(_plan_record_path(engine_path), encoding="utf-8") as stream:
            record = json.load(stream)
        return [str(name) for name in record["kept_fp32"]], [str(name) for name in record.get("skipped", [])]
    except (OSError, ValueError, KeyError, TypeError):
        return None, []


class TensorRTBackend(EngineBackend):
    """Runs an ONNX model through a cached TensorRT engine.

    Args:
        model_path: the ONNX file.
        precision: "fp32" or "fp16".
        engine_cache_dir: engine cache folder (None: `default_engine_cache_dir()`).
        trt: tensorrt module to use (tests inject a fake); None imports tensorrt.
        memory: device memory adapter (tests inject a fake); None creates `CudaMemory()`.
        precision_plan_path: FP16 precision plan JSON (`precision_plan.py`); None or "" for none.

    Attributes:
        engine_path: the cached engine file.
        engine_was_built: True when this backend built it (False: loaded from the cache).
        kept_fp32_layers: layers the precision plan kept in FP32 (None without a plan).

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
        precision_plan_path: Optional[str] = None,
    ) -> None:
        self.model_path = require_model_file(model_path)
        self._precision = normalize_precision(precision)
        try:
            self.precision_plan = load_precision_plan(precision_plan_path)
        except PrecisionPlanError as error:
            raise BackendError(str(error)) from error
        self._adapter = TensorRTAdapter(trt)
        self._memory = memory if memory is not None else CudaMemory()
        self._engine, self.engine_path, self.engine_was_built, self.kept_fp32_layers = load_or_build_engine(
            self._adapter, self.model_path, self._precision, self._memory.gpu_name(), engine_cache_dir,
            self.precision_plan,
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
