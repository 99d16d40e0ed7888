"""Engine backends behind one interface, chosen by name ("onnxruntime" or "tensorrt").

The backends are a :class:`leapnbv_common.registry.Registry` (:data:`ENGINE_BACKENDS`) of factories
``(model_path, precision, settings) -> EngineBackend``: the built-in ones import their runtime only
when chosen, and :func:`register_backend` adds another (a plug-in, or a test) without editing this
file; the ``backend`` parameter names it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple

from leapnbv_common.registry import Registry
from leapnbv_perception.backends.base import (
    BackendError,
    EngineBackend,
    ModelFileNotFoundError,
    TensorSpec,
    normalize_precision,
    require_model_file,
)

# The built-in backends (ENGINE_BACKENDS.names() also lists registered ones).
BACKEND_NAMES = ("onnxruntime", "tensorrt")
# Tests only: onnxruntime with every output moved by one ulp (LastBitNudgedOnnxRuntimeBackend); the regression's
# numeric-configuration test selects it, nothing else does.
LAST_BIT_NUDGED_BACKEND = "onnxruntime_last_bit_nudged"


@dataclass(frozen=True)
class BackendSettings:
    """Every backend setting of the engine parameters; each backend reads the ones it has (see create_backend)."""

    providers: Optional[Tuple[str, ...]] = None
    engine_cache_dir: Optional[str] = None
    intra_op_threads: int = 0
    precision_plan_path: Optional[str] = None
    graph_optimization: str = "all"
    parallel_execution: bool = False
    inter_op_threads: int = 1
    thread_spinning: bool = True


# (model_path, normalized precision, settings) -> a ready backend.
BackendFactory = Callable[[str, str, BackendSettings], EngineBackend]


def _onnxruntime(model_path: str, precision: str, settings: BackendSettings, last_bit_nudged: bool = False
                 ) -> EngineBackend:
    from leapnbv_perception.backends.onnxruntime_backend import LastBitNudgedOnnxRuntimeBackend, OnnxRuntimeBackend

    return (LastBitNudgedOnnxRuntimeBackend if last_bit_nudged else OnnxRuntimeBackend)(
        model_path, providers=None if settings.providers is None else list(settings.providers),
        intra_op_threads=settings.intra_op_threads, precision=precision,
        graph_optimization=settings.graph_optimization, parallel_execution=settings.parallel_execution,
        inter_op_threads=settings.inter_op_threads, thread_spinning=settings.thread_spinning,
    )


def _tensorrt(model_path: str, precision: str, settings: BackendSettings) -> EngineBackend:
    from leapnbv_perception.backends.tensorrt_backend import TensorRTBackend

    return TensorRTBackend(model_path, precision=precision, engine_cache_dir=settings.engine_cache_dir,
                           precision_plan_path=settings.precision_plan_path)


def _check_factory(factory: object) -> None:
    if not callable(factory):
        raise TypeError(f"an engine backend must be a factory (model_path, precision, settings), got {factory!r}")


ENGINE_BACKENDS: Registry[BackendFactory] = Registry("engine backend", check=_check_factory)
ENGINE_BACKENDS.register("onnxruntime", _onnxruntime)
ENGINE_BACKENDS.register("tensorrt", _tensorrt)
ENGINE_BACKENDS.register(LAST_BIT_NUDGED_BACKEND,
                         lambda model_path, precision, settings: _onnxruntime(model_path, precision, settings, True))


def register_backend(name: str, factory: BackendFactory) -> None:
    """Make a backend factory selectable as ``name`` (lower case; replacing one of the same name)."""
    ENGINE_BACKENDS.register(name.strip().lower(), factory, replace=True)


def create_backend(
    name: str,
    model_path: str,
    precision: str = "fp32",
    providers: Optional[Sequence[str]] = None,
    engine_cache_dir: Optional[str] = None,
    intra_op_threads: int = 0,
    precision_plan_path: Optional[str] = None,
    graph_optimization: str = "all",
    parallel_execution: bool = False,
    inter_op_threads: int = 1,
    thread_spinning: bool = True,
) -> EngineBackend:
    """Create the named backend for one ONNX model.

    Args:
        name: "onnxruntime" or "tensorrt" (or a registered backend; case and spaces ignored).
        model_path: the ONNX file.
        precision: "fp32" or "fp16" (onnxruntime always runs the model as exported).
        providers: onnxruntime execution providers; default CPU only.
        engine_cache_dir: TensorRT engine cache folder; default next to the ONNX file.
        intra_op_threads: onnxruntime intra-op threads (0 = its default).
        precision_plan_path: TensorRT FP16 precision plan JSON (layers kept in FP32; see
            backends/precision_plan.py); None or "" for none. onnxruntime ignores it.
        graph_optimization, parallel_execution, inter_op_threads, thread_spinning: onnxruntime's session settings
            (OnnxRuntimeBackend); TensorRT ignores them.

    Returns:
        A ready EngineBackend.

    Raises:
        ModelFileNotFoundError: when model_path does not exist (message names it).
        ValueError: for an unknown backend name (the message lists the known ones) or precision.
        BackendError: when the runtime cannot load the model (or the precision plan is invalid).
    """
    factory = ENGINE_BACKENDS.get((name or "").strip().lower())
    require_model_file(model_path)
    settings = BackendSettings(
        providers=None if providers is None else tuple(providers), engine_cache_dir=engine_cache_dir,
        intra_op_threads=intra_op_threads, precision_plan_path=precision_plan_path,
        graph_optimization=graph_optimization, parallel_execution=parallel_execution,
        inter_op_threads=inter_op_threads, thread_spinning=thread_spinning)
    return factory(model_path, normalize_precision(precision), settings)


__all__ = [
    "BACKEND_NAMES",
    "ENGINE_BACKENDS",
    "LAST_BIT_NUDGED_BACKEND",
    "BackendError",
    "BackendFactory",
    "BackendSettings",
    "EngineBackend",
    "ModelFileNotFoundError",
    "TensorSpec",
    "create_backend",
    "register_backend",
]
