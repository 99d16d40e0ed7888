"""The shared camera-pose source: checked poses remembered by stamp, bad ones counted and dropped."""
from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseStamped  # noqa: E402

from leapnbv_common.camera_pose import (  # noqa: E402
    CAMERA_POSE_SOURCES,
    camera_pose_from_msg,
    create_camera_pose_source,
)
from leapnbv_common.conversions import ConversionError, header_with_stamp, pose_msg  # noqa: E402
from leapnbv_common.diagnostics import StageDiagnostics  # noqa: E402

pytestmark = pytest.mark.ros


def _pose(stamp_ns: int, position=(1.0, 2.0, 1.2), quaternion=None) -> PoseStamped:
    msg = PoseStamped(header=header_with_stamp(stamp_ns, "map"), pose=pose_msg(np.eye(3), np.array(position)))
    if quaternion is not None:
        q = msg.pose.orientation
        q.x, q.y, q.z, q.w = quaternion
    return msg


def test_a_unit_pose_is_read_and_others_are_refused():
    pose = camera_pose_from_msg(_pose(5))
    assert (pose.stamp_ns, pose.frame_id) == (5, "map")
    np.testing.assert_allclose(pose.position, [1.0, 2.0, 1.2])
    with pytest.raises(ConversionError, match=r"\|q\| = 2.0000"):
        camera_pose_from_msg(_pose(5, quaternion=(0.0, 0.0, 0.0, 2.0)))
    with pytest.raises(ConversionError, match="not a unit quaternion"):
        camera_pose_from_msg(_pose(5, quaternion=(float("nan"), 0.0, 0.0, 1.0)))
    with pytest.raises(ConversionError, match="position is not finite"):
        camera_pose_from_msg(_pose(5, position=(0.0, float("inf"), 0.0)))


def test_topic_source_remembers_by_stamp_and_counts_bad_poses():
    rclpy.init()
    try:
        node = rclpy.create_node("camera_pose_test")
        node.diagnostics = StageDiagnostics(node)
        arrived = []
        source = create_camera_pose_source("topic", node, capacity=2, on_pose=arrived.append)
        for stamp in (1, 2, 3):
            source._on_message(_pose(stamp))
        source._on_message(_pose(4, quaternion=(0.0, 0.0, 0.0, 2.0)))
        assert source.pose_at(1) is None  # only the newest two are remembered
        assert source.pose_at(3).stamp_ns == 3 and source.pose_at(4) is None
        assert [p.stamp_ns for p in arrived] == [1, 2, 3]
        assert node.diagnostics.rejected["bad_camera_pose"] == 1
        with pytest.raises(ValueError, match="unknown camera pose source 'gps'; known: tf, topic"):
            create_camera_pose_source("gps", node, capacity=2)
        assert CAMERA_POSE_SOURCES.names() == ["tf", "topic"]
        assert node.count_subscribers("camera_pose") == 1
        source.destroy()
        source.destroy()  # safe twice
        assert node.count_subscribers("camera_pose") == 0 and list(node.subscriptions) == []
        node.destroy_node()
    finally:
        rclpy.shutdown()


def test_another_source_is_one_class_registered_from_its_own_file():
    """docs/ARCHITECTURE.md's trace: a source registered outside camera_pose is made by the nodes' call."""
    from leapnbv_common.camera_pose import camera_pose_source, checked_camera_pose
    from leapnbv_common.pulled_input import PulledInput

    @camera_pose_source("fixed_for_test")
    class FixedCameraPoseSource:
        """Every frame's pose is one fixed pose (a camera on a tripod)."""

        def __init__(self, node, capacity, on_pose=None):
            self.on_pose = on_pose

        def pose_at(self, stamp_ns, camera_frame=""):
            return checked_camera_pose(stamp_ns, "map", [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1.5])

        def expect(self, stamp_ns, camera_frame=""):
            if self.on_pose is not None:
                self.on_pose(self.pose_at(stamp_ns, camera_frame))

        def destroy(self):
            self.on_pose = None  # nothing made on the node

    rclpy.init()
    try:
        node = rclpy.create_node("camera_pose_plugin_test")
        node.diagnostics = StageDiagnostics(node)
        arrived = []
        source = create_camera_pose_source("fixed_for_test", node, 5, arrived.append)
        assert PulledInput.adopt(node, source) is None  # no subscription: nothing to pull
        assert source.pose_at(7, "camera_color_optical_frame").position[2] == 1.5
        source.expect(8)
        assert [p.stamp_ns for p in arrived] == [8]
        assert "fixed_for_test" in CAMERA_POSE_SOURCES.names()
        with pytest.raises(TypeError, match="lacks pose_at, expect, destroy"):
            camera_pose_source("not_a_source")(object())
        node.destroy_node()
    finally:
        CAMERA_POSE_SOURCES.unregister("fixed_for_test")
        rclpy.shutdown()
