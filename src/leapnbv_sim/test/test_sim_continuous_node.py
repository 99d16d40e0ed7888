"""The simulator node's continuous mode: the motion stack follows a CURRENT goal's base path.

It stops on a withdrawn goal, renders each frame where the robot is at its stamp and publishes /clock before it.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from nav_msgs.msg import Path  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402

from leapnbv_common.conversions import path_msg, set_stamp  # noqa: E402
from leapnbv_msgs.msg import GoalStatus  # noqa: E402
from leapnbv_perception.smplx_layer import SMPLXModel  # noqa: E402
from leapnbv_sim.generation import SceneConfig, generate_scene  # noqa: E402
from leapnbv_sim.nodes.simulator_node import SimulatorNode  # noqa: E402
from leapnbv_sim.poses import camera_heading  # noqa: E402
from leapnbv_stand_ins.stand_in_body_model import build_stand_in_body_model  # noqa: E402

pytestmark = pytest.mark.ros
T0 = 7_000_000_000
PERIOD = 100_000_000  # 10 Hz


def _status(state: int, goal_stamp: int, changed: bool) -> GoalStatus:
    msg = GoalStatus(state=state, goal_changed=changed, commitment="FIRST_GOAL" if changed else "KEPT")
    set_stamp(msg.goal_stamp, goal_stamp)
    set_stamp(msg.committed_since, goal_stamp)
    return msg


def _path_in_optical_frame(sim: SimulatorNode, stamp: int, world_points: np.ndarray, heading: float) -> Path:
    """A base path as nbv_node publishes it: poses in the optical frame of the frame of ``stamp``."""
    observation = sim.camera_pose_at(stamp)
    assert observation is not None
    positions = (world_points - observation.position) @ observation.rotation
    level = np.array([[np.cos(heading), -np.sin(heading), 0.0], [np.sin(heading), np.cos(heading), 0.0],
                      [0.0, 0.0, 1.0]])
    rotations = np.repeat((observation.rotation.T @ level)[None], len(world_points), axis=0)
    msg = path_msg(rotations, positions)
    msg.header.frame_id = sim.frame_id
    set_stamp(msg.header.stamp, stamp)
    for pose in msg.poses:
        pose.header = msg.header
    return msg


@pytest.fixture(scope="module")
def scene():
    return generate_scene(SceneConfig(seed=1), SMPLXModel(build_stand_in_body_model("small"), source="stand_in_small"))


def test_motion_stack_follows_the_path_stops_on_withdrawal_and_publishes_the_clock(scene) -> None:
    context = rclpy.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    try:
        sim = SimulatorNode(scene=scene, context=context, parameter_overrides=[
            Parameter("rate_hz", value=0.0), Parameter("motion_stack", value=True),
            Parameter("publish_clock", value=True), Parameter("publish_obstacle_map", value=False),
            Parameter("publish_tf", value=False)])
        nodes.append(sim)
        clocks = []
        listener = rclpy.create_node("continuous_clock_listener", context=context)
        nodes.append(listener)
        listener.create_subscription(Clock, "/clock", lambda m: clocks.append(m.clock.sec * 10**9 + m.clock.nanosec),
                                     10)
        executor.add_node(sim)
        executor.add_node(listener)
        deadline = time.monotonic() + 20.0
        while sim.count_subscribers("/clock") < 1 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)

        start = scene.start_camera.copy()
        sim.publish_frame(T0)
        heading = camera_heading(start)
        forward = np.array([np.cos(heading), np.sin(heading), 0.0])
        base = np.array([start.position[0], start.position[1], 0.0])
        goal_points = np.array([base, base + 1.0 * forward, base + 2.0 * forward])
        # nbv_node's order: the status of the goal, then its path.
        sim.on_goal_status(_status(GoalStatus.STATE_CURRENT, T0, True))
        sim.on_base_path(_path_in_optical_frame(sim, T0, goal_points, heading))
        assert sim.robot is not None and sim.robot.stack.has_path and sim.last_path_stamp_ns == T0
        np.testing.assert_allclose(sim.last_path_world, goal_points, atol=1e-9)

        # 1 s of frames from rest, straight ahead at 0.5 m/s^2: 0.25 m; the camera keeps its height and heading.
        for k in range(1, 11):
            _, frame = sim.publish_frame(T0 + k * PERIOD)
        moved = frame.camera_pose.position - start.position
        assert moved @ forward == pytest.approx(0.25, abs=1e-9)
        assert np.linalg.norm(moved - (moved @ forward) * forward) < 1e-9
        assert sim.robot.stack.state.v == pytest.approx(0.5)
        np.testing.assert_allclose(sim.camera_pose_at(T0 + 10 * PERIOD).position, frame.camera_pose.position)

        # A kept goal's path replaces the one followed (replan_kept_goals); its status says KEPT.
        stamp = T0 + 10 * PERIOD
        sim.on_goal_status(_status(GoalStatus.STATE_CURRENT, stamp, False))
        sim.on_base_path(_path_in_optical_frame(sim, stamp, goal_points, heading))
        assert sim.robot.paths_taken == 2 and sim.robot.stack.state.v == pytest.approx(0.5)

        # Withdrawn (STALE): it brakes from 0.5 m/s at 0.5 m/s^2, 0.25 m in 1 s, and stands.
        sim.on_goal_status(_status(GoalStatus.STATE_STALE, stamp, False))
        assert not sim.robot.stack.has_path and sim.robot.withdrawals == 1
        before = frame.camera_pose.position
        for k in range(11, 26):
            _, frame = sim.publish_frame(T0 + k * PERIOD)
        assert (frame.camera_pose.position - before) @ forward == pytest.approx(0.25, abs=1e-9)
        assert sim.robot.stack.state.v == 0.0

        # A path of a stamp never rendered is refused; an empty path is a withdrawal.
        sim.on_base_path(_path_in_optical_frame(sim, T0, goal_points, heading))
        assert sim.robot.stack.has_path
        unknown = _path_in_optical_frame(sim, T0, goal_points, heading)
        set_stamp(unknown.header.stamp, T0 + 1)
        sim.robot.withdraw()
        sim.on_base_path(unknown)
        assert not sim.robot.stack.has_path
        sim.on_base_path(Path())
        assert not sim.robot.stack.has_path

        deadline = time.monotonic() + 10.0
        while (not clocks or clocks[-1] != T0 + 25 * PERIOD) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert clocks and clocks[-1] == T0 + 25 * PERIOD  # /clock went out at each frame's stamp
        assert clocks == sorted(clocks)
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_a_goal_withdrawn_while_the_target_is_not_seen_starts_the_search(scene) -> None:
    from leapnbv_msgs.msg import TargetTrack
    from leapnbv_sim.simulator import SEARCH_LOOKING, SEARCH_NONE

    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        sim = SimulatorNode(scene=scene, context=context, parameter_overrides=[
            Parameter("rate_hz", value=0.0), Parameter("motion_stack", value=True),
            Parameter("publish_obstacle_map", value=False), Parameter("publish_tf", value=False)])
        start = scene.start_camera.copy()
        heading = camera_heading(start)
        forward = np.array([np.cos(heading), np.sin(heading), 0.0])
        base = np.array([start.position[0], start.position[1], 0.0])
        goal_points = np.array([base, base + 1.0 * forward, base + 2.0 * forward])
        sim.publish_frame(T0)

        def status(state, goal_stamp, target_state, target_stamp, fixed_frame="sim_world"):
            msg = _status(state, goal_stamp, state == GoalStatus.STATE_CURRENT)
            msg.target = TargetTrack(state=target_state, fixed_frame=fixed_frame)
            set_stamp(msg.target.header.stamp, target_stamp)
            msg.target.position.x, msg.target.position.y, msg.target.position.z = 3.0, 2.0, 0.9
            return msg

        # Seen at the first frame: that camera is where a search drives back to.
        sim.on_goal_status(status(GoalStatus.STATE_CURRENT, T0, TargetTrack.STATE_TRACKED, T0))
        sim.on_base_path(_path_in_optical_frame(sim, T0, goal_points, heading))
        np.testing.assert_allclose(sim.robot._seen_from, start.position[:2])
        for k in range(1, 11):
            sim.publish_frame(T0 + k * PERIOD)
        stamp = T0 + 10 * PERIOD
        # Withdrawn with the target in view: a plain stop.
        sim.on_goal_status(status(GoalStatus.STATE_STALE, stamp, TargetTrack.STATE_TRACKED, stamp))
        assert sim.robot.search_phase == SEARCH_NONE and sim.robot.withdrawals == 1
        # A new goal, then withdrawn with the target not seen: the search, the head toward its last known place.
        sim.on_goal_status(status(GoalStatus.STATE_CURRENT, stamp, TargetTrack.STATE_TRACKED, stamp))
        sim.on_base_path(_path_in_optical_frame(sim, stamp, goal_points, heading))
        sim.on_goal_status(status(GoalStatus.STATE_STALE, stamp, TargetTrack.STATE_NOT_SEEN, stamp))
        assert sim.robot.search_phase == SEARCH_LOOKING and sim.robot.searches == 1
        np.testing.assert_allclose(sim.robot._target_xy, [3.0, 2.0])
        # The loss's empty path, after its status or before it: the same search, the same counts (two topics).
        sim.on_base_path(Path())
        assert sim.robot.search_phase == SEARCH_LOOKING and (sim.robot.searches, sim.robot.withdrawals) == (1, 2)
        sim.robot.withdraw()
        sim.on_goal_status(status(GoalStatus.STATE_CURRENT, stamp, TargetTrack.STATE_TRACKED, stamp))
        sim.on_base_path(_path_in_optical_frame(sim, stamp, goal_points, heading))
        sim.on_base_path(Path())
        assert sim.robot.search_phase == SEARCH_NONE and sim.robot.withdrawals == 3
        sim.on_goal_status(status(GoalStatus.STATE_STALE, stamp, TargetTrack.STATE_NOT_SEEN, stamp))
        assert sim.robot.search_phase == SEARCH_LOOKING and (sim.robot.searches, sim.robot.withdrawals) == (2, 3)
        # A place in another fixed frame is not used (the last ring centre is looked at instead).
        sim.robot.withdraw()
        sim.robot.look_at_target(np.array([1.0, 1.0, 0.0]))
        sim.on_goal_status(status(GoalStatus.STATE_NONE, stamp, TargetTrack.STATE_LOST, stamp, fixed_frame="odom"))
        assert sim.robot.search_phase == SEARCH_LOOKING and sim.robot.searches == 3
        np.testing.assert_allclose(sim.robot._target_xy, [1.0, 1.0])
        sim.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
