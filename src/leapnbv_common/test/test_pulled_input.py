"""Pulled inputs do not wake the node and hand over what waited, in order; the diagnostics count the
messages a node never took (from the publisher's sequence numbers) and every drop by reason."""
from __future__ import annotations

import time

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from leapnbv_common.diagnostics import StageDiagnostics  # noqa: E402
from leapnbv_common.pulled_input import PulledInput  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture()
def node():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("pulled_input_test", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=context)


def spin(executor, seconds: float) -> int:
    """Spin for a while; returns how many times the executor woke up."""
    cycles, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.1)
        cycles += 1
    return cycles


def test_a_pulled_input_waits_in_the_reader_until_drained(node):
    node, executor = node
    got = []
    diagnostics = StageDiagnostics(node)
    pulled = PulledInput.create(node, Header, "/pulled_input_test", lambda msg, info: (
        got.append(msg.frame_id), diagnostics.input_seen("frames", info)), QoSProfile(depth=4))
    publisher = node.create_publisher(Header, "/pulled_input_test", QoSProfile(depth=10,
                                                                               reliability=ReliabilityPolicy.RELIABLE))
    spin(executor, 0.5)  # discovery
    for i in range(3):
        publisher.publish(Header(frame_id=str(i)))
    cycles = spin(executor, 0.5)
    assert got == [] and cycles <= 8  # no wake-up per message, and no busy loop over unread data
    assert pulled.drain() == 3 and got == ["0", "1", "2"]
    for i in range(3, 10):  # seven while the node is "busy": the reader keeps the newest four
        publisher.publish(Header(frame_id=str(i)))
    spin(executor, 0.3)
    assert pulled.drain() == 4 and got[3:] == ["6", "7", "8", "9"]
    assert diagnostics.dropped["frames_not_taken"] == 3  # 3, 4, 5: counted from the sequence numbers
    assert pulled.drain() == 0


def test_drops_are_counted_by_reason_apart_from_rejections(node):
    node, _ = node
    diagnostics = StageDiagnostics(node)
    on_drop = diagnostics.drop_callback()
    on_drop("depth_evicted", 1)
    on_drop("depth_evicted", 2)
    diagnostics.drop("graph_busy", 3)
    values = {kv.key: kv.value for kv in diagnostics.status().values}
    assert values["dropped.depth_evicted"] == "2" and values["dropped.graph_busy"] == "3"
    assert values["dropped_total"] == "5" and values["rejected_total"] == "0"
    assert diagnostics.status().message == "ok"  # drops are the cost of keeping up: the status stays OK
