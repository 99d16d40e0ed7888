"""Loading an engine inside a node: never fatal, retried, reported in diagnostics."""
from __future__ import annotations

from typing import Any, Callable, Optional

from leapnbv_perception.params import EngineParams


class RetryingLoader:
    """Calls `load()` now and again every `retry_period_s` until it succeeds.

    A missing model file or a model that breaks its contract is logged with the error (which
    names the path), reported as an ERROR in diagnostics, and the node keeps serving: it
    rejects frames as "engine_not_ready" until a later retry loads the model.
    """

    def __init__(self, node, diagnostics, what: str, load: Callable[[], Any], retry_period_s: float) -> None:
        self._node = node
        self._diagnostics = diagnostics
        self._what = what
        self._load = load
        self.value: Optional[Any] = None
        self._timer = None
        if not self.try_load() and retry_period_s > 0:
            self._timer = node.create_timer(retry_period_s, self._retry)

    def try_load(self) -> bool:
        try:
            self.value = self._load()
        except Exception as exc:  # noqa: BLE001 - any load failure is reported, never fatal
            message = f"{self._what} not loaded: {type(exc).__name__}: {exc}"
            self._node.get_logger().error(message, throttle_duration_sec=30.0)
            self._diagnostics.set_engine_state(message, ok=False)
            return False
        self._node.get_logger().info(f"{self._what} loaded")
        self._diagnostics.set_engine_state("ready", ok=True)
        return True

    def _retry(self) -> None:
        if self.try_load() and self._timer is not None:
            self._timer.cancel()

    @staticmethod
    def load_in_configure(node, what: str, load: Callable[[], Any]) -> Any:
        """Load in a managed node's ``configure_stage``: the value, or the failure with the same text as above.

        The lifecycle retries the whole configure (leapnbv_common.managed_node), so nothing is retried here.

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
