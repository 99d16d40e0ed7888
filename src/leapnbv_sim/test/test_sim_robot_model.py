"""Tests of the simulated robot (leapnbv_sim.poses.RobotModel): a goal moves the base, the camera stays mounted."""
from __future__ import annotations

import numpy as np
import pytest

from leapnbv_sim.poses import (
    CameraPose,
    RobotModel,
    camera_heading,
    camera_pitch,
    look_at_pose,
    mounted_camera_pose,
)
from leapnbv_sim.simulator import SimulatorParams, robot_model


def test_a_goal_at_the_mounting_height_is_reached_exactly():
    start = look_at_pose(np.array([-3.0, 0.0, 1.2]), np.array([0.0, 0.0, 0.9]))
    goal = look_at_pose(np.array([1.0, 2.0, 1.2]), np.array([0.0, 0.0, 0.9]))
    reached = RobotModel().reach(start, goal)
    np.testing.assert_allclose(reached.position, goal.position, atol=1e-12)
    np.testing.assert_allclose(reached.rotation, goal.rotation, atol=1e-12)


def test_a_goal_off_the_mounting_height_keeps_the_camera_mounted():
    # A goal 1.5 m too high and rolled (from a slanted floor): the base goes under it, the camera stays at 1.2 m.
    start = look_at_pose(np.array([-3.0, 0.0, 1.2]), np.array([0.0, 0.0, 0.9]))
    level = look_at_pose(np.array([1.0, 2.0, 2.7]), np.array([0.0, 0.0, 0.9]))
    roll = np.array([[np.cos(0.3), -np.sin(0.3), 0.0], [np.sin(0.3), np.cos(0.3), 0.0], [0.0, 0.0, 1.0]])
    goal = CameraPose(level.rotation @ roll, level.position)
    reached = RobotModel().reach(start, goal)
    np.testing.assert_allclose(reached.position, [1.0, 2.0, 1.2], atol=1e-12)
    assert camera_heading(reached) == pytest.approx(camera_heading(goal), abs=1e-9)
    assert camera_pitch(reached) == pytest.approx(camera_pitch(goal), abs=1e-9)  # the pan-tilt head follows
    assert reached.rotation[2, 0] == pytest.approx(0.0, abs=1e-12)  # no roll: x stays level
    fixed = RobotModel(head="fixed").reach(start, goal)
    assert camera_pitch(fixed) == pytest.approx(camera_pitch(start), abs=1e-9)  # the mounting pitch
    mounted = RobotModel(camera_height=0.6).reach(start, goal)
    assert mounted.position[2] == pytest.approx(0.6)
    free = RobotModel(motion="free").reach(start, goal)
    np.testing.assert_array_equal(free.rotation, goal.rotation)
    np.testing.assert_array_equal(free.position, goal.position)


def test_heading_and_pitch_of_known_cameras():
    camera = look_at_pose(np.array([0.0, 0.0, 1.0]), np.array([0.0, 2.0, 0.0]))
    assert camera_heading(camera) == pytest.approx(np.pi / 2)
    assert camera_pitch(camera) == pytest.approx(np.arctan2(1.0, 2.0))
    down = mounted_camera_pose(camera, 1.0, head="fixed", pitch_rad=np.radians(90.0) - 1e-9)
    assert camera_heading(down) == pytest.approx(np.pi / 2, abs=1e-6)


def test_bad_robot_settings_are_refused():
    with pytest.raises(ValueError, match="robot motion"):
        RobotModel(motion="fly")
    with pytest.raises(ValueError, match="robot head"):
        RobotModel(head="none")
    with pytest.raises(ValueError, match="mounting height"):
        mounted_camera_pose(look_at_pose(np.zeros(3) + [0, 0, 1.0], np.array([1.0, 0, 1.0])), 0.0)


def test_the_simulator_parameters_describe_the_robot():
    params = SimulatorParams()
    assert robot_model(params) == RobotModel("base", "pan_tilt", 0.0)
