"""Loading an engine inside a managed node's configure: never fatal, the reason reported, retried by the lifecycle."""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

from leapnbv_perception.params import EngineParams


def load_in_configure(node, what: str, load: Callable[[], Any]) -> Any:
    """Load an engine or model in a managed node's ``configure_stage``: the value, or the configure fails.

    The lifecycle retries the whole configure (``configure_retry_period_s``, leapnbv_common.managed_node), so
    nothing is retried here: a missing model file leaves the node unconfigured with the reason (which names the
    path) on /diagnostics, and a later configure loads it once the file is there.

    Raises:
        StageNotReadyError: "<what> not loaded: <error type>: <error>" (the node stays unconfigured with it).
    """
    from leapnbv_common.managed_node import StageNotReadyError

    try:
        value = load()
    except Exception as exc:  # noqa: BLE001 - any load failure is the configure's reason
        raise StageNotReadyError(f"{what} not loaded: {type(exc).__name__}: {exc}") from exc
    node.get_logger().info(f"{what} loaded")
    return value


def create_engine_backend(params: EngineParams):
    """The engine backend an EngineParams instance names (onnxruntime or tensorrt) for its model file."""
    from leapnbv_perception.backends import create_backend

    return create_backend(params.backend, params.model_file_path, precision=params.precision,
                          providers=list(params.providers), engine_cache_dir=params.engine_cache_dir or None,
                          intra_op_threads=params.intra_op_threads,
                          precision_plan_path=params.precision_plan_path or None,
                          graph_optimization=params.graph_optimization, parallel_execution=params.parallel_execution,
                          inter_op_threads=params.inter_op_threads, thread_spinning=params.thread_spinning)


def load_person_detector(params: Any, backend: str = "") -> Any:
    """A PersonDetector on the engine that DetectorParams name, loaded.

    Args:
        params: The node's DetectorParams.
        backend: Another backend for the engine (the timing stand-in's onnxruntime, whatever the
            ground_truth backend says); empty: the params' own.
    """
    from leapnbv_perception.detector import PersonDetector

    engine_params = dataclasses.replace(params, backend=backend) if backend else params
    return PersonDetector(create_engine_backend(engine_params), params.score_threshold, params.iou_threshold,
                          params.max_detections, family=params.detector_family, multi_label=params.multi_label)
