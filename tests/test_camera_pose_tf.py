"""The TF camera-pose source over DDS: real tf2_msgs/TFMessage messages on /tf and /tf_static.

A probe node publishes a robot's tree (``map -> odom -> base_link`` on /tf, ``base_link -> camera_link
-> camera_color_optical_frame`` on /tf_static, transient-local) and a second node, in its own
context, owns a TfCameraPoseSource (``camera_pose_source: tf``). Checked: the wire (type name, type
hash and CDR bytes are the ROS distro's tf2_msgs/TFMessage), interpolation through the chain,
``expect`` and ``on_pose``, and the errors: a missing transform, an extrapolation (by how much), a
parent that changes, a bad transform, a pose below the floor.
"""
from __future__ import annotations

import time
from typing import Callable, List

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from node_harness import Probe  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from leapnbv_common.camera_pose import StampedCameraPose, create_camera_pose_source  # noqa: E402
from leapnbv_common.camera_pose.tf_messages import tf_message  # noqa: E402
from leapnbv_common.diagnostics import StageDiagnostics  # noqa: E402
from leapnbv_common.qos import tf_qos, tf_static_qos  # noqa: E402
from leapnbv_common.tf_buffer import (  # noqa: E402
    ExtrapolationError,
    MissingTransformError,
    StampedTransform,
    Transform,
)
from leapnbv_common.topics import TF_STATIC_TOPIC, TF_TOPIC  # noqa: E402

pytestmark = pytest.mark.ros

S = 1_000_000_000
CAMERA = "camera_color_optical_frame"
OPTICAL = [-0.5, 0.5, -0.5, 0.5]  # camera_link (x forward, z up) -> optical (x right, y down, z forward)
MOUNT = [0.1, 0.0, 1.2]


def yaw(angle: float) -> List[float]:
    return [0.0, 0.0, float(np.sin(angle / 2)), float(np.cos(angle / 2))]


def link(parent: str, child: str, stamp_ns: int, rotation, translation) -> StampedTransform:
    return StampedTransform(parent, child, stamp_ns, Transform.checked(rotation, translation))


def static_links() -> List[StampedTransform]:
    return [link("base_link", "camera_link", 0, yaw(0.0), MOUNT),
            link("camera_link", CAMERA, 0, OPTICAL, [0.0, 0.0, 0.0])]


def base_links(stamp_ns: int, x: float, heading: float, parent: str = "odom") -> List[StampedTransform]:
    return [link("map", "odom", stamp_ns, yaw(0.0), [0.0, 0.5, 0.0]),
            link(parent, "base_link", stamp_ns, yaw(heading), [x, 0.0, 0.0])]


def expected_camera(x: float, heading: float) -> np.ndarray:
    """(4, 4) T_map_camera written out by hand: base at (x, 0.5) facing ``heading``, camera 0.1 m ahead, 1.2 m up,
    its optical axis along the heading."""
    c, s = np.cos(heading), np.sin(heading)
    m = np.eye(4)
    m[:3, :3] = np.column_stack([[s, -c, 0.0], [0.0, 0.0, -1.0], [c, s, 0.0]])  # optical x right, y down, z ahead
    m[:3, 3] = [x + 0.1 * c, 0.5 + 0.1 * s, 1.2]
    return m


def pose_matrix(pose: StampedCameraPose) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = pose.rotation, pose.position
    return m


class SourceNode:
    """A node of its own context that owns a TF camera-pose source, as ground_node and nbv_node do."""

    def __init__(self) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("tf_pose_user", context=self.context)
        self.node.diagnostics = StageDiagnostics(self.node)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.handed: List[StampedCameraPose] = []
        self.source = create_camera_pose_source("tf", self.node, 50, self.handed.append)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


@pytest.fixture(scope="module")
def wire():
    probe = Probe("tf_probe")
    user = SourceNode()
    tf_pub = probe.node.create_publisher(TFMessage, TF_TOPIC, tf_qos())
    static_pub = probe.node.create_publisher(TFMessage, TF_STATIC_TOPIC, tf_static_qos(1))
    static_pub.publish(tf_message(static_links()))  # before the user's reader matched: transient-local delivers it

    def spin_until(predicate: Callable[[], bool], timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            probe.executor.spin_once(timeout_sec=0.005)
            user.executor.spin_once(timeout_sec=0.005)
            if predicate():
                return True
        return False

    assert spin_until(lambda: tf_pub.get_subscription_count() >= 1 and static_pub.get_subscription_count() >= 1)
    assert spin_until(lambda: user.source.listener.messages >= 1), "the latched /tf_static never came"
    try:
        yield {"probe": probe, "user": user, "tf": tf_pub, "static": static_pub, "spin_until": spin_until}
    finally:
        user.close()
        probe.close()


def publish(wire, links: List[StampedTransform]) -> None:
    before = wire["user"].source.listener.messages
    wire["tf"].publish(tf_message(links))
    assert wire["spin_until"](lambda: wire["user"].source.listener.messages > before)


def test_the_wire_is_the_distros_tf2_msgs(wire):
    rosbags_typesys = pytest.importorskip("rosbags.typesys")
    store = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
    probe = wire["probe"]
    (endpoint,) = probe.node.get_publishers_info_by_topic(TF_TOPIC)
    assert endpoint.topic_type == "tf2_msgs/msg/TFMessage"
    # The type hash DDS discovery carries (RIHS01 of the type description) is the one of Jazzy's definition.
    assert str(endpoint.topic_type_hash) == store.hash_rihs01("tf2_msgs/msg/TFMessage")
    # CDR bytes: rclpy's serialization of our message = rosbags' of its built-in tf2_msgs/msg/TFMessage.
    msg = tf_message(base_links(1_234_567_891, 2.5, 0.3) + static_links())
    Time, Header = store.types["builtin_interfaces/msg/Time"], store.types["std_msgs/msg/Header"]
    Vector3, Quaternion = store.types["geometry_msgs/msg/Vector3"], store.types["geometry_msgs/msg/Quaternion"]
    Tf, Ts = store.types["geometry_msgs/msg/Transform"], store.types["geometry_msgs/msg/TransformStamped"]
    theirs = store.types["tf2_msgs/msg/TFMessage"](transforms=[
        Ts(header=Header(stamp=Time(sec=t.header.stamp.sec, nanosec=t.header.stamp.nanosec),
                         frame_id=t.header.frame_id),
           child_frame_id=t.child_frame_id,
           transform=Tf(translation=Vector3(x=t.transform.translation.x, y=t.transform.translation.y,
                                            z=t.transform.translation.z),
                        rotation=Quaternion(x=t.transform.rotation.x, y=t.transform.rotation.y,
                                            z=t.transform.rotation.z, w=t.transform.rotation.w)))
        for t in msg.transforms])
    ours, reference = bytes(serialize_message(msg)), bytes(store.serialize_cdr(theirs, "tf2_msgs/msg/TFMessage"))
    assert len(ours) == len(reference) == 396
    # rclpy's serializer leaves the alignment padding after a string as the buffer had it (rosbags writes
    # zeros): every byte rosbags wrote as non-zero is the same, and each side reads the other's bytes back.
    assert bytes(o if r else 0 for o, r in zip(ours, reference)) == reference
    assert store.deserialize_cdr(ours, "tf2_msgs/msg/TFMessage") == theirs
    assert deserialize_message(reference, TFMessage) == msg


def test_the_pose_at_a_stamp_between_two_transforms_is_interpolated_through_the_chain(wire):
    user = wire["user"]
    publish(wire, base_links(10 * S, 1.0, 0.0))
    publish(wire, base_links(11 * S, 2.0, 0.2))
    pose = user.source.pose_at(10 * S + 250_000_000, CAMERA)
    assert pose is not None and pose.frame_id == "map" and pose.stamp_ns == 10 * S + 250_000_000
    np.testing.assert_allclose(pose_matrix(pose), expected_camera(1.25, 0.05), atol=1e-9)
    # As the tree's newest stamp advanced, each pose was handed on (what ground_node learns poses from).
    assert [p.stamp_ns for p in user.handed][-2:] == [10 * S, 11 * S]
    np.testing.assert_allclose(pose_matrix(user.handed[-1]), expected_camera(2.0, 0.2), atol=1e-9)


def test_an_expected_pose_is_handed_on_once_its_transforms_come(wire):
    user = wire["user"]
    stamp = 11 * S + 500_000_000
    assert user.source.pose_at(stamp, CAMERA) is None
    assert isinstance(user.source.last_error, ExtrapolationError) and user.source.last_error.by_ns == 500_000_000
    user.source.expect(stamp, CAMERA)
    assert not user.source.timer.is_canceled()  # the wait timer runs while a frame waits
    publish(wire, base_links(12 * S, 3.0, 0.4))
    assert wire["spin_until"](lambda: any(p.stamp_ns == stamp for p in user.handed))
    (pose,) = (p for p in user.handed if p.stamp_ns == stamp)
    np.testing.assert_allclose(pose_matrix(pose), expected_camera(2.5, 0.3), atol=1e-9)
    assert wire["spin_until"](lambda: user.source.timer.is_canceled(), 1.0)  # nothing waits: the timer stops


def test_a_missing_transform_names_the_frame(wire):
    user = wire["user"]
    with pytest.raises(MissingTransformError, match="source frame 'camera_depth_optical_frame' does not exist"):
        user.source.lookup(12 * S, "camera_depth_optical_frame")
    assert user.source.pose_at(12 * S, "camera_depth_optical_frame") is None
    assert isinstance(user.source.last_error, MissingTransformError)


def test_an_extrapolation_says_by_how_much(wire):
    user = wire["user"]
    future = (r"into the future: 'odom' -> 'base_link' at 13250000000 ns is 1\.250 s after its buffered time "
              r"\[10000000000, 12000000000\] ns")
    with pytest.raises(ExtrapolationError, match=future) as error:
        user.source.lookup(13 * S + 250_000_000, CAMERA)
    assert error.value.by_ns == 1_250_000_000
    with pytest.raises(ExtrapolationError, match=r"into the past: .* 0\.500 s before"):
        user.source.lookup(9 * S + 500_000_000, CAMERA)


def test_a_parent_that_changes_the_newest_wins(wire):
    user = wire["user"]
    publish(wire, [link("world", "base_link", 14 * S, yaw(0.0), [5.0, 0.0, 0.0])])  # re-parented away from odom
    with pytest.raises(MissingTransformError, match="'map' and 'camera_color_optical_frame' are not connected"):
        user.source.lookup(14 * S, CAMERA)
    assert user.source.pose_at(14 * S, CAMERA) is None
    publish(wire, base_links(15 * S, 6.0, 0.0))  # and back under odom: connected again
    np.testing.assert_allclose(pose_matrix(user.source.pose_at(15 * S, CAMERA)), expected_camera(6.0, 0.0), atol=1e-9)
    with pytest.raises(ExtrapolationError):  # the samples under the old parent went with it
        user.source.lookup(12 * S, CAMERA)


def test_a_bad_transform_is_counted_and_the_rest_of_its_message_used(wire):
    user = wire["user"]
    msg = tf_message(base_links(16 * S, 7.0, 0.0))
    msg.transforms[0].transform.rotation.w = 2.0  # map -> odom: |q| = 2
    before = user.source.listener.messages
    wire["tf"].publish(msg)
    assert wire["spin_until"](lambda: user.source.listener.messages > before)
    assert user.node.diagnostics.rejected["bad_transform"] == 1
    assert user.source.store.lookup("odom", "base_link", 16 * S).translation[0] == 7.0
    with pytest.raises(ExtrapolationError):
        user.source.lookup(16 * S, CAMERA)  # map -> odom of 16 s never came


def test_a_camera_below_the_floor_breaks_the_pose_contract(wire):
    user = wire["user"]
    links = base_links(17 * S, 8.0, 0.0)
    links[0] = link("map", "odom", 17 * S, yaw(0.0), [0.0, 0.5, -2.0])  # the fixed frame's floor 0.8 m above it
    publish(wire, links)
    assert user.source.pose_at(17 * S, CAMERA) is None
    assert user.node.diagnostics.rejected["bad_camera_pose"] >= 1


def _tf_subscriptions(node) -> List[str]:
    return sorted(s.topic_name for s in node.subscriptions if s.topic_name in (TF_TOPIC, TF_STATIC_TOPIC))


def test_destroy_releases_the_sources_tf_subscriptions_and_its_timer():
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("tf_pose_destroyed", context=context)
        node.diagnostics = StageDiagnostics(node)
        timers_before = len(list(node.timers))
        source = create_camera_pose_source("tf", node, 5)
        assert _tf_subscriptions(node) == [TF_TOPIC, TF_STATIC_TOPIC]
        assert len(list(node.timers)) == timers_before + 1
        source.expect(3 * S, CAMERA)  # a frame waiting: the wait timer runs
        source.destroy()
        assert _tf_subscriptions(node) == [] and len(list(node.timers)) == timers_before
        source.destroy()  # safe twice
        source.expect(4 * S, CAMERA)  # and a late expect neither fails nor restarts anything
        assert source.pose_at(4 * S, CAMERA) is None
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_a_cleanup_then_configure_cycle_leaves_one_set_of_tf_subscriptions():
    """ground_node on the TF source, configured, cleaned up, configured again, activated, and so on.

    Each configure makes the source's /tf and /tf_static subscriptions once, each cleanup ends them.
    """
    from leapnbv_geometry.nodes.ground_node import GroundNode

    rclpy.init(args=["--ros-args", "-p", "camera_pose_source:=tf", "-p", "autostart:=false"])
    try:
        node = GroundNode()
        assert _tf_subscriptions(node) == []
        for _ in range(2):
            node.trigger_configure()
            assert node.lifecycle_state == "inactive"
            assert _tf_subscriptions(node) == [TF_TOPIC, TF_STATIC_TOPIC]
            source = node.pose_floors.source
            node.trigger_cleanup()
            assert node.lifecycle_state == "unconfigured"
            assert _tf_subscriptions(node) == [] and source.listener.subscriptions == []
        node.trigger_configure()
        node.trigger_activate()
        assert _tf_subscriptions(node) == [TF_TOPIC, TF_STATIC_TOPIC]
        node.trigger_deactivate()
        node.trigger_cleanup()
        assert _tf_subscriptions(node) == []
        node.shut_down()
        node.destroy_node()
    finally:
        rclpy.shutdown()
