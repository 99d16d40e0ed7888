"""TensorRT engine backend: builds an engine from the ONNX file on the device, caches it, runs it.

The backend is three modules, one concern each:

- `tensorrt_engine_cache`: the cache key and path, loading a cached engine or building it
  (rebuild on failure, the precision plan's record of FP32 layers);
- `tensorrt_adapter`: `TensorRTAdapter`, every call into `tensorrt` (build with the FP16
  precision plan, deserialize, describe, execute through the binding or the tensor API);
- this module: device memory (`CudaMemory`) and `TensorRTBackend`, which allocates one
  device buffer per engine tensor, binds them and runs the engine.

All but the adapter and the `CudaMemory` implementations is plain Python that the tests
exercise with a fake `tensorrt` module and fake CUDA libraries.

CUDA memory: `cuda-python` is tried first (`cuda.bindings.runtime`, or the older
`cuda.cudart`); when it is missing, or its first calls fail (a cuda-python built for CUDA 12
on JetPack 5's CUDA 11.4 driver answers cudaErrorInsufficientDriver, or a function its
driver lacks), the reason is logged and `pycuda` is used instead. Only when both fail does
the backend fail, naming both reasons. Neither library, nor `tensorrt`, is imported before a
TensorRT backend is actually created, so this module imports on machines without them.
"""

from __future__ import annotations

import logging
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np

from leapnbv_perception.backends.base import (
    BackendError,
    EngineBackend,
    Tensor,
    check_inputs,
    normalize_precision,
    require_model_file,
)
from leapnbv_perception.backends.precision_plan import PrecisionPlanError, load_precision_plan
from leapnbv_perception.backends.tensorrt_adapter import WORKSPACE_BYTES, TensorRTAdapter
from leapnbv_perception.backends.tensorrt_engine_cache import (
    ENGINE_CACHE_ENV,
    default_engine_cache_dir,
    engine_cache_key,
    engine_cache_path,
    external_data_digests,
    load_or_build_engine,
)

LOGGER = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------
# Device memory: the only code that touches CUDA
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

    def copy_to_device(self, pointer: int, host: Tensor) -> None:
        host = np.ascontiguousarray(host)
        kind = self._cudart.cudaMemcpyKind.cudaMemcpyHostToDevice
        self._check(self._cudart.cudaMemcpy(pointer, host.ctypes.data, host.nbytes, kind), "cudaMemcpy")

    def copy_to_host(self, host: Tensor, pointer: int) -> None:
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

    def copy_to_device(self, pointer: int, host: Tensor) -> None:
        self._driver.memcpy_htod(self._allocations[pointer], np.ascontiguousarray(host))

    def copy_to_host(self, host: Tensor, pointer: int) -> None:
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

# ----------------------------------------------------------------------------------------
# The backend: buffers, bindings, run
# ----------------------------------------------------------------------------------------


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
        self._host_outputs: Dict[str, Tensor] = {}
        self._device: Dict[str, int] = {}
        shapes: Dict[str, Tuple[int, ...]] = {}
        for name, spec in list(self._inputs.items()) + list(self._outputs.items()):
            shape = tuple(dim for dim in spec.shape if isinstance(dim, int) and dim >= 0)
            if len(shape) != len(spec.shape):
                raise BackendError(
                    "engine from '%s' has a dynamic shape for '%s' %s; export with static shapes"
                    % (self.model_path, name, spec.shape)
                )
            shapes[name] = shape
            nbytes = int(np.prod(shape)) * np.dtype(spec.dtype).itemsize
            self._device[name] = self._memory.allocate(nbytes)
        for name, spec in self._outputs.items():
            self._host_outputs[name] = np.empty(shapes[name], dtype=spec.dtype)
        if not self._tensor_api:
            self._bindings = [self._device[name] for name in self._adapter.binding_order(self._engine)]

    @property
    def uses_tensor_api(self) -> bool:
        """True when the engine runs through the TensorRT 10 tensor API."""
        return self._tensor_api

    def run(self, inputs: Mapping[str, Tensor]) -> Dict[str, Tensor]:
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


__all__ = [
    "CUDA_DRIVER_ERRORS",
    "CUDA_MEMORY_LIBRARIES",
    "ENGINE_CACHE_ENV",
    "WORKSPACE_BYTES",
    "CudaMemory",
    "CudaPythonMemory",
    "CudaUnavailable",
    "PyCudaMemory",
    "TensorRTAdapter",
    "TensorRTBackend",
    "default_engine_cache_dir",
    "engine_cache_key",
    "engine_cache_path",
    "external_data_digests",
    "load_or_build_engine",
]
