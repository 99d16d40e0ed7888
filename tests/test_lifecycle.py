"""Managed nodes over DDS, driven as a robot user does (``ros2 lifecycle get/set``) and as the manager does.

Configure fails on a missing model (the reason reported, the node unconfigured),
succeeds once the file is there, activate makes the node serve, deactivate stops its output, cleanup
releases, shutdown ends the process with 0.

The stage under test is the real detector_node once it is a ManagedNode (its model_file_path missing,
then the contract detector copied there); until then the test's own managed node
(tests/lifecycle_test_node.py: configure reads a model file, activate answers strings). See
``stage_under_test``.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List

import pytest

pytest.importorskip("rclpy")

import node_harness as harness  # noqa: E402
from node_harness import diag_value, lifecycle_get, lifecycle_set, lifecycle_transitions  # noqa: E402

from leapnbv_bringup.lifecycle_manager import LifecycleManager  # noqa: E402
from leapnbv_common.managed_node import ManagedNode  # noqa: E402
from leapnbv_common.qos import stage_output_qos  # noqa: E402

pytestmark = pytest.mark.ros

TEST_NODE = str(Path(__file__).with_name("lifecycle_test_node.py"))


@dataclass
class StageUnderTest:
    """A managed node whose configure needs a model file, and how to feed it and read its output."""

    name: str
    module: str  # module name or script path (node_harness.start_node)
    params: Dict[str, str]  # everything but model_file_path
    install: Callable[[str], None]  # make the model file appear at this path
    send: Callable[[Any, Any, int], None]  # (probe, publisher, i): publish one input
    input_topic: str
    input_type: Any
    output_topic: str
    output_type: Any

    def start(self, namespace: str, log: Path, model_path: str, **params: str) -> subprocess.Popen:
        return harness.start_node(self.module, str(log), namespace=namespace,
                                  params={**self.params, "model_file_path": model_path, **params})


def _detector_is_managed() -> bool:
    try:
        from leapnbv_perception.nodes.detector_node import DetectorNode
    except ImportError:
        return False
    return issubclass(DetectorNode, ManagedNode)


def stage_under_test() -> StageUnderTest:
    """The real detector_node when it is a ManagedNode, else the test's own managed node.

    The test's node stands in until the stage nodes move onto ManagedNode; nothing else in this file
    changes then.
    """
    if _detector_is_managed():
        from sensor_msgs.msg import Image

        from leapnbv_common.conversions import numpy_to_image
        from leapnbv_msgs.msg import PersonDetections
        from leapnbv_stand_ins.files import ensure_contract_models

        def install(path: str) -> None:
            shutil.copy(ensure_contract_models()[0], path)

        def send(probe, publisher, i: int) -> None:
            import numpy as np
            from std_msgs.msg import Header

            rgb = np.zeros((240, 320, 3), np.uint8)
            rgb[60:200, 140:180] = (200, 30, 30)
            header = Header(frame_id="camera_color_optical_frame")
            header.stamp.sec, header.stamp.nanosec = 1000 + i, 0
            publisher.publish(numpy_to_image(rgb, "rgb8", header))

        return StageUnderTest("detector_node", "leapnbv_perception.nodes.detector_node",
                              {"backend": "onnxruntime", "precision": "fp32", "intra_op_threads": "1",
                               "multi_label": "true"}, install, send, "image", Image, "detections",
                              PersonDetections)
    from std_msgs.msg import String

    def write_model(path: str) -> None:
        Path(path).write_text("weights-v1")

    def send_text(probe, publisher, i: int) -> None:
        publisher.publish(String(data=f"frame {i}"))

    return StageUnderTest("model_stage", TEST_NODE, {}, write_model, send_text, "model_stage_in", String,
                          "model_stage_out", String)


STAGE = stage_under_test()


class Feed:
    """The probe's publisher of the stage's input and what comes out of it."""

    def __init__(self, probe: harness.Probe, namespace: str) -> None:
        self.probe = probe
        self.publisher = probe.node.create_publisher(STAGE.input_type, f"{namespace}/{STAGE.input_topic}",
                                                     stage_output_qos(10))
        self.outputs: List[Any] = probe.collect(STAGE.output_type, f"{namespace}/{STAGE.output_topic}")
        self.sent = 0

    def served(self, timeout_s: float = 20.0) -> bool:
        """Send inputs (one every 0.5 s) until an output comes."""
        before = len(self.outputs)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.sent += 1
            STAGE.send(self.probe, self.publisher, self.sent)
            if self.probe.spin_until(lambda: len(self.outputs) > before, 0.5):
                return True
        return False

    def silent_for(self, seconds: float) -> bool:
        """Send inputs for `seconds`: True when nothing came out."""
        before = len(self.outputs)
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.sent += 1
            STAGE.send(self.probe, self.publisher, self.sent)
            self.probe.spin_for(0.25)
        return len(self.outputs) == before


def latest_status(probe: harness.Probe, name: str, predicate, timeout_s: float = 10.0):
    assert probe.spin_until(lambda: probe.status_where(name, predicate) is not None, timeout_s), \
        probe.statuses.get(name, [None])[-1]
    return probe.status_where(name, predicate)


@pytest.fixture()
def probe():
    probe = harness.Probe("lifecycle_probe")
    yield probe
    probe.close()


def test_ros2_lifecycle_set_configure_fails_without_the_model_then_each_transition(probe, tmp_path):
    ns = "/lc_set"
    name = f"{ns}/{STAGE.name}"
    model = tmp_path / "model.bin"
    proc = STAGE.start(ns, tmp_path / "node.log", str(model), autostart="false")
    try:
        feed = Feed(probe, ns)
        assert lifecycle_get(probe, name) == "unconfigured"
        assert {"configure", "shutdown"} <= set(lifecycle_transitions(probe, name))
        # Unconfigured, it already reports on /diagnostics.
        latest_status(probe, name, lambda s: diag_value(s, "lifecycle_state", "") == "unconfigured")

        assert not lifecycle_set(probe, name, "configure")  # the model is missing
        assert lifecycle_get(probe, name) == "unconfigured"
        status = latest_status(probe, name, lambda s: str(model) in diag_value(s, "lifecycle_reason", ""))
        assert status.level == status.ERROR and str(model) in status.message
        assert diag_value(status, "lifecycle_reason").startswith("configure failed: ")
        assert diag_value(status, "lifecycle_state") == "unconfigured"
        assert feed.publisher.get_subscription_count() == 0  # nothing subscribes before activate

        STAGE.install(str(model))
        assert lifecycle_set(probe, name, "configure")
        assert lifecycle_get(probe, name) == "inactive"
        assert "activate" in lifecycle_transitions(probe, name)
        latest_status(probe, name, lambda s: diag_value(s, "lifecycle_state", "") == "inactive"
                      and s.level == s.OK)
        assert feed.silent_for(1.0)  # inactive: no subscription, no output

        assert lifecycle_set(probe, name, "activate")
        assert lifecycle_get(probe, name) == "active"
        assert feed.served(), harness.read_log(proc)[-3000:]

        assert lifecycle_set(probe, name, "deactivate")
        assert lifecycle_get(probe, name) == "inactive"
        assert probe.spin_until(lambda: feed.publisher.get_subscription_count() == 0, 10.0)
        assert feed.silent_for(1.5)

        assert lifecycle_set(probe, name, "cleanup")
        assert lifecycle_get(probe, name) == "unconfigured"
        assert not lifecycle_set(probe, name, "activate")  # not from unconfigured
        assert lifecycle_set(probe, name, "configure") and lifecycle_set(probe, name, "activate")
        assert feed.served()

        assert lifecycle_set(probe, name, "shutdown")  # from active: releases everything, the process ends
        assert proc.wait(timeout=20) == 0
    finally:
        harness.stop_node(proc)
    log = harness.read_log(proc)
    assert "Traceback" not in log, log


def test_manager_retries_configure_until_the_model_appears_and_brings_a_restarted_node_up(probe, tmp_path):
    ns = "/lc_manager"
    name = f"{ns}/{STAGE.name}"
    model = tmp_path / "late_model.bin"
    events: List[str] = []
    proc = STAGE.start(ns, tmp_path / "node.log", str(model), autostart="false")
    manager = LifecycleManager(probe.node, [name], configure_retry_s=0.5, on_event=events.append)
    try:
        feed = Feed(probe, ns)
        record = manager.state(name)
        assert probe.spin_until(lambda: record.failed and str(model) in record.reason, 60.0), (record, events)
        assert record.managed and record.state == "unconfigured"
        assert record.reason.startswith("configure failed: ") and str(model) in record.reason
        assert any(str(model) in e and "trying again every 0.5 s" in e for e in events), events
        assert probe.spin_until(lambda: record.configure_attempts >= 3, 20.0)  # retried
        assert lifecycle_get(probe, name) == "unconfigured"
        assert "unconfigured: configure failed" in manager.describe(name)
        status = manager.diagnostic_status("/test/lifecycle_manager")
        assert status.level == status.ERROR and STAGE.name in status.message

        STAGE.install(str(model))
        assert probe.spin_until(lambda: record.state == "active", 30.0), (record, events)
        assert not record.failed and record.reason == ""
        assert any(e.startswith(f"{STAGE.name} active") and "configure attempts" in e for e in events), events
        assert manager.diagnostic_status("/test/lifecycle_manager").level == status.OK
        assert feed.served(), harness.read_log(proc)[-3000:]

        # A new process of the node (kill -9, started again as a supervisor would): the manager sees its
        # new process on /diagnostics and brings it up again.
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        harness.stop_node(proc)
        killed = time.monotonic()
        proc = STAGE.start(ns, tmp_path / "node2.log", str(model), autostart="false")
        assert probe.spin_until(lambda: any("runs in a new process" in e for e in events), 60.0), events
        assert probe.spin_until(lambda: record.since > killed and record.state == "active", 60.0), (record, events)
        assert lifecycle_get(probe, name) == "active"
        assert feed.served(), harness.read_log(proc)[-3000:]
    finally:
        manager.close()
        harness.stop_node(proc)
    assert "Traceback" not in harness.read_log(proc)


def test_the_launch_files_manager_node_brings_the_node_up(probe, tmp_path):
    ns = "/lc_launch"
    name = f"{ns}/{STAGE.name}"
    model = tmp_path / "model.bin"
    STAGE.install(str(model))
    proc = STAGE.start(ns, tmp_path / "node.log", str(model), autostart="false")
    manager = subprocess.Popen(
        [sys.executable, "-m", "leapnbv_bringup.lifecycle_manager", "--ros-args", "-r", f"__ns:={ns}",
         "-p", f"node_names:=[{STAGE.name}]", "-p", "autostart:=true"],
        stdout=open(tmp_path / "manager.log", "w"), stderr=subprocess.STDOUT,  # noqa: SIM115
        env=dict(os.environ, PYTHONUNBUFFERED="1"), start_new_session=True)
    try:
        feed = Feed(probe, ns)
        status = latest_status(probe, f"{ns}/lifecycle_manager",
                               lambda s: diag_value(s, f"{STAGE.name}.state", "") == "active", 60.0)
        assert status.level == status.OK and status.message == "ok"
        assert lifecycle_get(probe, name) == "active"
        assert feed.served(), harness.read_log(proc)[-3000:]
        manager.send_signal(signal.SIGINT)
        assert manager.wait(timeout=20) == 0
    finally:
        if manager.poll() is None:
            manager.kill()
            manager.wait()
        harness.stop_node(proc)
    assert "Traceback" not in (tmp_path / "manager.log").read_text()


def test_a_node_started_alone_configures_itself_and_retries_until_the_model_appears(probe, tmp_path):
    ns = "/lc_alone"
    name = f"{ns}/{STAGE.name}"
    model = tmp_path / "model.bin"
    proc = STAGE.start(ns, tmp_path / "node.log", str(model), configure_retry_period_s="0.3")  # autostart default
    try:
        feed = Feed(probe, ns)
        status = latest_status(probe, name, lambda s: str(model) in s.message, 60.0)
        assert diag_value(status, "lifecycle_state") == "unconfigured" and status.level == status.ERROR
        STAGE.install(str(model))
        latest_status(probe, name, lambda s: diag_value(s, "lifecycle_state", "") == "active"
                      and s.level == s.OK, 30.0)
        assert feed.served(), harness.read_log(proc)[-3000:]
        assert harness.stop_with_signal(proc, signal.SIGINT) == 0
    finally:
        harness.stop_node(proc)
    assert "Traceback" not in harness.read_log(proc)


def test_a_bad_parameter_value_still_ends_a_managed_node_with_exit_2(tmp_path):
    proc = STAGE.start("/lc_bad", tmp_path / "node.log", str(tmp_path / "m.bin"), configure_retry_period_s="-1.0")
    try:
        assert proc.wait(timeout=60) == 2
    finally:
        harness.stop_node(proc)
    log = harness.read_log(proc)
    program = Path(STAGE.module).stem if STAGE.module.endswith(".py") else STAGE.module.rsplit(".", 1)[-1]
    assert f"[{program}] cannot start:" in log and "configure_retry_period_s" in log and "Traceback" not in log, log


def test_graph_runner_brings_a_managed_node_up_reports_its_failure_and_restarts_it_through_the_lifecycle(
        probe, tmp_path):
    """The runner with a managed node in raster_node's place: failure reported, retried, restarted.

    The test's node runs as a module, so that the runner's warm standby can become it. It is reported
    and retried while its model is missing, serves once it is there, and after a kill -9 its standby
    comes up through configure and activate again.
    """
    from std_msgs.msg import String

    from leapnbv_bringup.graph import NodeSpec
    from leapnbv_bringup.graph_runner import GraphError, GraphRunner, RestartPolicy

    model = tmp_path / "model.bin"
    events: List[str] = []
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(TEST_NODE).parent),
                                                       os.environ.get("PYTHONPATH", "")]))
    runner = GraphRunner(None, {"raster_node": {"model_file_path": str(model)}}, log_dir=str(tmp_path / "logs"),
                         env=env, nodes=["raster_node"], on_event=events.append, configure_retry_s=0.5,
                         restart=RestartPolicy(max_restarts=3, spare_delay_s=0.5))
    spec = NodeSpec("raster_node", "tests", "lifecycle_test_node", remaps={"__node": "raster_node"})
    runner.nodes = [spec]
    runner._states["raster_node"].spec = spec
    spin = lambda t: probe.executor.spin_once(timeout_sec=t)  # noqa: E731
    outputs = probe.collect(String, "/leapnbv/model_stage_out")
    publisher = probe.node.create_publisher(String, "/leapnbv/model_stage_in", stage_output_qos(10))

    def served() -> bool:
        before = len(outputs)
        for i in range(40):
            publisher.publish(String(data=f"frame {i}"))
            if probe.spin_until(lambda: len(outputs) > before, 0.5):
                return True
        return False

    try:
        runner.start()
        runner.wait_ready(probe.node, 60.0, spin=spin, require_all=False)
        failed = runner.failed_nodes()
        assert list(failed) == ["raster_node"], (failed, runner.not_ready(0.0), events)
        assert failed["raster_node"].startswith("unconfigured: configure failed: FileNotFoundError: ")
        assert str(model) in failed["raster_node"]
        assert any("raster_node: configure failed" in e and "trying again every 0.5 s" in e for e in events), events
        with pytest.raises(GraphError, match=r"raster_node: unconfigured: configure failed: .*model\.bin"):
            runner.wait_ready(probe.node, 2.0, spin=spin)  # require_all: what the regression uses
        status = runner.diagnostic_status()
        values = {kv.key: kv.value for kv in status.values}
        assert status.level == status.ERROR and "raster_node unconfigured" in status.message
        assert values["raster_node.lifecycle"] == "unconfigured" and str(model) in values["raster_node.serving"]
        assert lifecycle_get(probe, "/leapnbv/raster_node") == "unconfigured"

        model.write_text("weights-v2")
        assert probe.spin_until(lambda: not runner.not_ready(0.0), 30.0), (runner.not_ready(0.0), events)
        assert lifecycle_get(probe, "/leapnbv/raster_node") == "active"
        values = {kv.key: kv.value for kv in runner.diagnostic_status().values}
        assert (values["raster_node.lifecycle"], values["raster_node.serving"]) == ("active", "yes")
        assert served(), harness.read_log_path(tmp_path / "logs" / "raster_node.log")

        runner.watch_diagnostics(probe.node)
        assert probe.spin_until(lambda: runner.spares_ready()["raster_node"], 60.0), events
        old_pid = runner.processes["raster_node"].pid
        os.kill(old_pid, signal.SIGKILL)
        assert probe.spin_until(lambda: any("raster_node serving again (active)" in e for e in events), 60.0), events
        assert runner.processes["raster_node"].pid != old_pid
        assert any("raster_node restarted (warm spare" in e for e in events), events
        assert not runner.not_ready(0.0)
        assert lifecycle_get(probe, "/leapnbv/raster_node") == "active"
        outputs.clear()
        assert served()
    finally:
        codes = runner.stop()
    assert codes == {"raster_node": 0}, runner.stop_report


@pytest.mark.slow
def test_the_graph_plans_once_a_missing_model_file_appears(probe, tmp_path):
    """The whole graph on the simulator's frames, hmr_node's body model missing at start.

    The runner reports hmr_node and runs the rest; no goal comes while hmr_node has no model; the file
    appears, the retry loads it (a managed hmr_node: the lifecycle manager's configure; until then the
    node's own engine retry) and the graph plans.
    """
    from geometry_msgs.msg import PoseStamped

    from leapnbv_bringup.graph_runner import GraphRunner, perception_overrides
    from leapnbv_common.qos import latched_goal_qos
    from leapnbv_common.topics import NEXT_BEST_VIEW_TOPIC
    from leapnbv_stand_ins.files import ensure_stand_in_body_model

    body = tmp_path / "late_body.npz"
    overrides = perception_overrides("ground_truth", body_model=str(body))
    overrides["hmr_node"]["configure_retry_period_s"] = "1.0"
    events: List[str] = []
    runner = GraphRunner(None, overrides, log_dir=str(tmp_path / "logs"), on_event=events.append,
                         configure_retry_s=1.0)
    goals: List[PoseStamped] = []
    probe.node.create_subscription(PoseStamped, NEXT_BEST_VIEW_TOPIC, goals.append, latched_goal_qos())
    spin = lambda t: probe.executor.spin_once(timeout_sec=t)  # noqa: E731
    sim = None
    try:
        runner.start()
        runner.wait_ready(probe.node, 120.0, spin=spin, require_all=False)
        failed = runner.failed_nodes()
        assert list(failed) == ["hmr_node"], (runner.not_ready(0.0), events)
        assert "late_body.npz" in failed["hmr_node"], failed
        sim = subprocess.Popen(
            [sys.executable, "-m", "leapnbv_sim.nodes.simulator_node", "--ros-args", "-p", "rate_hz:=2.0",
             "-p", "scene_seed:=3", "-r", f"goal:={NEXT_BEST_VIEW_TOPIC}"],
            stdout=open(tmp_path / "simulator.log", "w"), stderr=subprocess.STDOUT,  # noqa: SIM115
            env=dict(os.environ, PYTHONUNBUFFERED="1"), start_new_session=True)
        probe.spin_for(5.0)
        assert not [g for g in goals if g.header.frame_id], "a goal without hmr_node"

        shutil.copy(ensure_stand_in_body_model("small"), body)
        assert probe.spin_until(lambda: not runner.not_ready(0.0), 60.0), (runner.not_ready(0.0), events)
        assert probe.spin_until(lambda: len([g for g in goals if g.header.frame_id]) >= 3, 90.0), events
    finally:
        if sim is not None:
            sim.send_signal(signal.SIGINT)
            try:
                sim.wait(timeout=20)
            except subprocess.TimeoutExpired:
                sim.kill()
                sim.wait()
        codes = runner.stop()
    assert set(codes.values()) == {0}, runner.stop_report
