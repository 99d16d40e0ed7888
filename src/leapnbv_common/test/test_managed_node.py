"""ManagedNode: the lifecycle of a small stage whose configure needs a file, in one process.

Configure fails while the file is missing (unconfigured, the reason on /diagnostics, what it made
released) and succeeds once it exists; activate makes its subscription and enables its lifecycle
publisher; deactivate and cleanup destroy what activate and configure made; shutdown releases
everything from any state; autostart retries configure; a ParamsError is not retried.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Set

import pytest

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from leapnbv_common.managed_node import ACTIVE, FINALIZED, INACTIVE, UNCONFIGURED, ManagedNode  # noqa: E402
from leapnbv_common.params import ParamsError, param  # noqa: E402

pytestmark = pytest.mark.ros


@dataclass
class FileStageParams:
    model_path: str = param("", "the file configure loads")
    suffix: str = param("!", "appended to every message")
    refuse: bool = param(False, "configure raises ParamsError")


class FileStage(ManagedNode):
    """Loads a text file in configure; while active, answers each input with the file's text + the input."""

    def __init__(self, **kwargs) -> None:
        super().__init__("file_stage", FileStageParams, hardware_id=lambda p: f"suffix {p.suffix}", **kwargs)
        self.model = None
        self.cleanups = 0
        self.changes: List[Set[str]] = []

    def configure_stage(self) -> None:
        p = self.params.value
        self.output = self.create_lifecycle_publisher(String, "file_stage_out", 10)
        self.create_timer(5.0, lambda: None)  # made before the failure: destroyed with it
        if p.refuse:
            raise ParamsError("refuse is set")
        with open(p.model_path) as handle:
            self.model = handle.read().strip()

    def activate_stage(self) -> None:
        self.create_subscription(String, "file_stage_in", self.on_input, 10)

    def on_input(self, msg: String) -> None:
        self.output.publish(String(data=f"{self.model}:{msg.data}{self.params.value.suffix}"))

    def cleanup_stage(self) -> None:
        self.cleanups += 1
        self.model = None

    def on_params_change(self, params, changed) -> None:
        self.changes.append(set(changed))


@pytest.fixture()
def context():
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    rclpy.shutdown(context=context)


class Harness:
    """The node under test and a probe in one executor."""

    def __init__(self, context, **overrides) -> None:
        params = [Parameter(k, value=v) for k, v in overrides.items()]
        self.node = FileStage(context=context, parameter_overrides=params)
        self.probe = rclpy.create_node("file_stage_probe", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self.outputs: List[str] = []
        self.statuses: List[DiagnosticStatus] = []
        self.probe.create_subscription(String, "file_stage_out", lambda m: self.outputs.append(m.data), 10)
        self.probe.create_subscription(DiagnosticArray, "/diagnostics", lambda m: self.statuses.extend(m.status), 10)
        self.input = self.probe.create_publisher(String, "file_stage_in", 10)

    def spin_until(self, predicate, timeout_s: float = 10.0) -> bool:
        import time

        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.02)
        return predicate()

    def answers(self, text: str) -> bool:
        """Send until an answer to `text` comes (the subscription may still be matching)."""
        for _ in range(20):
            self.input.publish(String(data=text))
            if self.spin_until(lambda: any(o.endswith(text + self.node.params.value.suffix) for o in self.outputs),
                               0.25):
                return True
        return False

    def status(self) -> DiagnosticStatus:
        """A status published now (those published before it are received and dropped first)."""
        self.spin_until(lambda: False, 0.2)
        self.statuses.clear()
        self.node.diagnostics.publish()
        assert self.spin_until(lambda: self.statuses and self.statuses[-1].name.endswith("file_stage"), 5.0)
        return self.statuses[-1]

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.probe.destroy_node()


def values(status: DiagnosticStatus) -> dict:
    return {kv.key: kv.value for kv in status.values}


def test_configure_fails_while_the_file_is_missing_and_succeeds_once_it_exists(context, tmp_path):
    model = tmp_path / "model.txt"
    h = Harness(context, model_path=str(model), autostart=False)
    try:
        node = h.node
        assert node.lifecycle_state == UNCONFIGURED and not node.autostart
        status = h.status()
        assert values(status)["lifecycle_state"] == UNCONFIGURED and status.hardware_id == "suffix !"
        base_publishers = {id(p) for p in node.publishers}
        base_timers = {id(t) for t in node.timers}

        assert node.trigger_configure().to_label() == "transition_failure"
        assert node.lifecycle_state == UNCONFIGURED
        assert node.lifecycle_reason.startswith("configure failed: FileNotFoundError: ")
        assert str(model) in node.lifecycle_reason
        status = h.status()
        assert status.level == DiagnosticStatus.ERROR and str(model) in status.message
        assert values(status)["lifecycle_reason"] == node.lifecycle_reason
        assert str(model) in values(status)["engine_state"]
        # What the half-made configure created is gone, and cleanup_stage ran on it.
        assert {id(p) for p in node.publishers} == base_publishers
        assert {id(t) for t in node.timers} == base_timers
        assert node.cleanups == 1
        assert node._retry_timer is None  # autostart off: the manager retries, not the node

        model.write_text("weights")
        assert node.trigger_configure().to_label() == "transition_success"
        assert node.lifecycle_state == INACTIVE and node.model == "weights" and node.lifecycle_reason == ""
        status = h.status()
        assert status.level == DiagnosticStatus.OK and values(status)["lifecycle_state"] == INACTIVE
        assert len({id(p) for p in node.publishers} - base_publishers) == 1
        assert not node.output.is_activated
        node.output.publish(String(data="dropped while inactive"))

        assert node.trigger_activate().to_label() == "transition_success"
        assert node.lifecycle_state == ACTIVE and node.output.is_activated
        assert h.answers("a")
        assert "weights:a!" in h.outputs and "dropped while inactive" not in h.outputs
        assert values(h.status())["lifecycle_state"] == ACTIVE

        # A runtime change while configured reaches the node; the output follows it.
        assert node.set_parameters([Parameter("suffix", value="?")])[0].successful
        assert node.changes == [{"suffix"}]
        assert h.answers("b") and "weights:b?" in h.outputs

        subscriptions = len(list(node.subscriptions))
        assert node.trigger_deactivate().to_label() == "transition_success"
        assert node.lifecycle_state == INACTIVE and len(list(node.subscriptions)) == subscriptions - 1
        count = len(h.outputs)
        h.input.publish(String(data="c"))
        h.spin_until(lambda: False, 0.5)
        assert len(h.outputs) == count  # no subscription, and the publisher is disabled

        assert node.trigger_cleanup().to_label() == "transition_success"
        assert node.lifecycle_state == UNCONFIGURED and node.model is None and node.cleanups == 2
        assert {id(p) for p in node.publishers} == base_publishers
        # Unconfigured: a parameter change is only stored (the next configure reads it).
        assert node.set_parameters([Parameter("suffix", value="#")])[0].successful
        assert node.changes == [{"suffix"}]

        assert node.trigger_shutdown().to_label() == "transition_success"
        assert node.lifecycle_state == FINALIZED and node.finalized
    finally:
        h.close()


def test_shutdown_from_active_releases_what_activate_and_configure_made(context, tmp_path):
    model = tmp_path / "model.txt"
    model.write_text("w")
    h = Harness(context, model_path=str(model), autostart=False)
    try:
        node = h.node
        before = (len(list(node.publishers)), len(list(node.subscriptions)), len(list(node.timers)))
        assert node.start_up() == ACTIVE
        assert len(list(node.subscriptions)) == before[1] + 1
        node.shut_down()
        assert node.lifecycle_state == FINALIZED and node.model is None and node.cleanups == 1
        assert (len(list(node.publishers)), len(list(node.subscriptions)), len(list(node.timers))) == before
        node.shut_down()  # twice: nothing more
        assert node.cleanups == 1
    finally:
        h.close()


def test_autostart_retries_configure_until_the_file_appears(context, tmp_path):
    model = tmp_path / "late.txt"
    h = Harness(context, model_path=str(model), configure_retry_period_s=0.1)
    try:
        node = h.node
        assert node.autostart
        assert h.spin_until(lambda: node.configure_attempts >= 3, 10.0)  # the first spin started it, then retries
        assert node.lifecycle_state == UNCONFIGURED and "late.txt" in node.lifecycle_reason
        model.write_text("late weights")
        assert h.spin_until(lambda: node.lifecycle_state == ACTIVE, 10.0)
        attempts = node.configure_attempts
        assert node._retry_timer is None
        assert h.answers("x") and "late weights:x!" in h.outputs
        h.spin_until(lambda: False, 0.3)
        assert node.configure_attempts == attempts  # no retry once configured
    finally:
        h.close()


def test_a_params_error_in_configure_is_not_retried(context, tmp_path):
    h = Harness(context, refuse=True, configure_retry_period_s=0.05)
    try:
        node = h.node
        with pytest.raises(ParamsError, match="refuse is set"):
            node.start_up()
        assert node.lifecycle_state == UNCONFIGURED and node.bad_parameters
        assert node.lifecycle_reason == "configure failed: ParamsError: refuse is set"
        h.spin_until(lambda: False, 0.3)
        assert node.configure_attempts == 1 and node._retry_timer is None
        # The parameter changed, a configure succeeds (the manager's or ros2 lifecycle set's).
        model = tmp_path / "m.txt"
        model.write_text("m")
        assert node.set_parameters([Parameter("refuse", value=False), Parameter("model_path", value=str(model))])
        assert node.trigger_configure().to_label() == "transition_success" and not node.bad_parameters
    finally:
        h.close()


def test_bad_parameter_values_refuse_the_node_in_its_constructor(context):
    from rclpy.exceptions import ParameterException

    # rclpy's range check of the declared descriptor (run_node makes either an exit 2 with one line).
    with pytest.raises((ParamsError, ParameterException), match="configure_retry_period_s"):
        FileStage(context=context, parameter_overrides=[Parameter("configure_retry_period_s", value=-1.0)])
