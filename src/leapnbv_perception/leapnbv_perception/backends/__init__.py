"""Engine backends behind one interface, chosen by name ("onnxruntime" or "tensorrt")."""

from __future__ import annotations

from typing import Optional, Sequence

from leapnbv_perception.backends.base import (
    BackendError,
    EngineBackend,
    ModelFileNotFoundError,
    TensorSpec,
    normalize_precision,
    require_model_file,
)

BACKEND_NAMES = ("onnxruntime", "tensorrt")


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
        name: "onnxruntime" or "tensorrt".
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
        ValueError: for an unknown backend name or precision.
        BackendError: when the runtime cannot load the model (or the precision plan is invalid).
    """
    key = (name or "").strip().lower()
    if key not in BACKEND_NAMES:
        raise ValueError("unknown backend '%s'; expected one of %s" % (name, ", ".join(BACKEND_NAMES)))
    require_model_file(model_path)
    precision = normalize_precision(precision)
    if key == "onnxruntime":
        from leapnbv_perception.backends.onnxruntime_backend import OnnxRuntimeBackend

        return OnnxRuntimeBackend(
            model_path, providers=providers, intra_op_threads=intra_op_threads, precision=precision,
            graph_optimization=graph_optimization, parallel_execution=parallel_execution,
            inter_op_threads=inter_op_threads, thread_spinning=thread_spinning,
        )
    from leapnbv_perception.backends.tensorrt_backend import TensorRTBackend

    return TensorRTBackend(
        model_path, precision=precision, engine_cache_dir=engine_cache_dir, precision_plan_path=precision_plan_path
    )


__all__ = [
    "BACKEND_NAMES",
    "BackendError",
    "EngineBackend",
    "ModelFileNotFoundError",
    "TensorSpec",
    "create_backend",
]
