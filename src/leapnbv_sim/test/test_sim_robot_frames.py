"""The simulated robot's TF tree: each camera pose split into base and head, published on /tf and /tf_static."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from leapnbv_common.tf_buffer import TransformBuffer
from leapnbv_sim.poses import CameraPose, RobotModel, camera_pose_from_base_goal, look_at_pose
from leapnbv_sim.robot_frames import RobotFrameIds, dynamic_links, static_links

IDS = RobotFrameIds()


def chain(camera: CameraPose, stamp_ns: int = 7) -> TransformBuffer:
    buffer = TransformBuffer()
    for link in static_links(IDS):
        buffer.set_transform(link, static=True)
    for link in dynamic_links(camera, stamp_ns, IDS):
        buffer.set_transform(link)
    return buffer


def assert_same_pose(transform, camera: CameraPose) -> None:
    np.testing.assert_allclose(transform.rotation_matrix(), camera.rotation, atol=1e-12)
    np.testing.assert_allclose(transform.translation, camera.position, atol=1e-12)


def test_the_chain_composes_to_the_camera_a_base_robot_reaches() -> None:
    observer = camera_pose_from_base_goal(np.array([0.5, -1.0]), 0.3, 1.25, pitch_rad=0.2)
    goal = look_at_pose(np.array([3.0, 2.0, 0.9]), np.array([1.0, 1.0, 0.8]))
    for head in ("pan_tilt", "fixed"):
        camera = RobotModel(motion="base", head=head).reach(observer, goal)
        buffer = chain(camera)
        assert_same_pose(buffer.lookup(IDS.world, IDS.camera, 7), camera)
        base = buffer.lookup(IDS.odom, IDS.base, 7)
        # The base stands on the floor under the camera, level, facing the camera's heading.
        np.testing.assert_allclose(base.translation, [3.0, 2.0, 0.0], atol=1e-12)
        heading = np.arctan2(1.0 - 2.0, 1.0 - 3.0)
        np.testing.assert_allclose(base.rotation, [0.0, 0.0, np.sin(heading / 2), np.cos(heading / 2)], atol=1e-12)
        # The head: straight above the base at the mounting height, tilted about its y axis only (no pan, no roll).
        mount = buffer.lookup(IDS.base, IDS.head, 7)
        np.testing.assert_allclose(mount.translation, [0.0, 0.0, 1.25], atol=1e-12)
        pitch = 0.2 if head == "fixed" else np.arcsin(-(camera.rotation[2, 2]))
        np.testing.assert_allclose(mount.rotation, [0.0, np.sin(pitch / 2), 0.0, np.cos(pitch / 2)], atol=1e-9)


def test_the_chain_composes_to_any_6dof_camera() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        x, y, z, w = q
        rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                             [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                             [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        camera = CameraPose(rotation, rng.uniform([-5, -5, 0.2], [5, 5, 3]))
        assert_same_pose(chain(camera).lookup(IDS.world, IDS.camera, 7), camera)


def _spin_until(executors, done, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        for executor in executors:
            executor.spin_once(timeout_sec=0.02)
    return done()


@pytest.mark.ros
def test_the_simulator_publishes_its_frames_on_tf_and_a_tf_source_reads_each_frames_pose() -> None:
    rclpy = pytest.importorskip("rclpy")
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from leapnbv_common.camera_pose import create_camera_pose_source
    from leapnbv_common.conversions import pose_to_numpy, stamp_to_ns
    from leapnbv_common.diagnostics import StageDiagnostics
    from leapnbv_common.qos import stage_input_qos
    from leapnbv_common.topics import CAMERA_POSE_TOPIC
    from leapnbv_perception.smplx_layer import SMPLXModel
    from leapnbv_sim.generation import SceneConfig, generate_scene
    from leapnbv_sim.nodes.simulator_node import SimulatorNode
    from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model

    scene = generate_scene(SceneConfig(seed=1), SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small"))
    # Frame names of this test alone: the trees of other simulators on the same ROS domain stay apart.
    tag = "_tf_test_%d" % os.getpid()
    names = {"world_frame_id": "world" + tag, "odom_frame_id": "odom" + tag, "base_frame_id": "base" + tag,
             "camera_link_frame_id": "camera_link" + tag, "frame_id": "camera_optical" + tag}
    context = rclpy.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    try:
        sim = SimulatorNode(scene=scene, context=context, parameter_overrides=[Parameter("rate_hz", value=0.0)] + [
            Parameter(name, value=value) for name, value in names.items()])
        nodes.append(sim)
        executor.add_node(sim)
        user = rclpy.create_node("tf_source_user", context=context, parameter_overrides=[
            Parameter("camera_pose_fixed_frame", value=names["world_frame_id"]),
            Parameter("camera_pose_camera_frame", value=names["frame_id"])])
        nodes.append(user)
        user.diagnostics = StageDiagnostics(user)
        handed = []
        source = create_camera_pose_source("tf", user, 10, handed.append)
        poses = []
        user.create_subscription(PoseStamped, CAMERA_POSE_TOPIC, lambda m: poses.append(m)
                                 if m.header.frame_id == names["world_frame_id"] else None, stage_input_qos(10))
        executor.add_node(user)
        assert _spin_until([executor], lambda: source.listener.messages >= 1, 20.0), "no /tf_static (latched)"
        assert _spin_until([executor], lambda: sim.tf_pub.get_subscription_count() >= 1
                           and sim.pose_pub.get_subscription_count() >= 1, 20.0)

        first_stamp, first = sim.publish_frame(stamp_ns=5_000_000_000)
        sim.move_to(look_at_pose(np.array([1.0, -2.0, 1.1]), np.array([0.0, 0.0, 1.0])))
        second_stamp, second = sim.publish_frame(stamp_ns=5_100_000_000)
        assert _spin_until([executor], lambda: len(handed) >= 2 and len(poses) >= 2, 20.0), \
            f"TF poses handed on: {[p.stamp_ns for p in handed]}; {source.last_error}"
        for stamp, frame, pose_msg in ((first_stamp, first, poses[0]), (second_stamp, second, poses[1])):
            pose = source.pose_at(stamp, names["frame_id"])
            assert pose is not None and pose.frame_id == names["world_frame_id"] and pose.stamp_ns == stamp
            np.testing.assert_allclose(pose.rotation, frame.camera_pose.rotation, atol=1e-9)
            np.testing.assert_allclose(pose.position, frame.camera_pose.position, atol=1e-9)
            # The same pose as the PoseStamped the simulator still publishes.
            rotation, position = pose_to_numpy(pose_msg.pose)
            assert stamp_to_ns(pose_msg.header.stamp) == stamp
            np.testing.assert_allclose(pose.rotation, rotation, atol=1e-9)
            np.testing.assert_allclose(pose.position, position, atol=1e-9)
        assert [p.stamp_ns for p in handed] == [first_stamp, second_stamp]
        assert not np.allclose(first.camera_pose.position, second.camera_pose.position)
        # Between the two frames the tree is interpolated: half way, the camera is half way.
        middle = source.pose_at((first_stamp + second_stamp) // 2, names["frame_id"])
        np.testing.assert_allclose(middle.position, 0.5 * (first.camera_pose.position + second.camera_pose.position),
                                   atol=1e-9)
    finally:
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown(context=context)
