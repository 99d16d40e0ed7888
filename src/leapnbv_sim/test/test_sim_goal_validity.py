"""The simulated motion stack honours a goal's valid_until on its own clock (DrivenRobot.drive)."""
from __future__ import annotations

import numpy as np
import pytest

from leapnbv_sim.motion_stack import BaseLimits
from leapnbv_sim.poses import look_at_pose
from leapnbv_sim.simulator import SEARCH_LOOKING, SEARCH_NONE, DrivenRobot

PERIOD_NS = 200_000_000  # 5 Hz frames


def _driving_robot() -> DrivenRobot:
    start = look_at_pose(np.array([0.0, 0.0, 1.2]), np.array([5.0, 0.0, 1.2]))
    robot = DrivenRobot(start, BaseLimits())
    rotation = look_at_pose(np.array([4.0, 0.0, 1.2]), np.array([5.0, 0.0, 1.2])).rotation
    assert robot.take_path(np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]]), rotation, goal_changed=True)
    return robot


def _drive(robot: DrivenRobot, frames: int) -> None:
    for frame in range(frames):
        robot.drive(frame * PERIOD_NS, (frame + 1) * PERIOD_NS)


def test_a_goal_is_followed_up_to_its_valid_until_and_braked_there() -> None:
    robot = _driving_robot()
    robot.hold_goal_until(5 * PERIOD_NS)  # a goal 1 s old at t = 1 s: still valid there, not after
    _drive(robot, 5)
    assert robot.stack.has_path and robot.withdrawals == 0 and robot.stack.state.v > 0.1
    now = 5 * PERIOD_NS
    robot.drive(now, now + PERIOD_NS)
    assert not robot.stack.has_path and robot.withdrawals == 1 and robot.search_phase == SEARCH_NONE
    robot.drive(now + PERIOD_NS, now + 2 * PERIOD_NS)
    assert robot.withdrawals == 1  # once


def test_the_step_is_split_at_valid_until() -> None:
    # valid_until inside a step: the robot drives up to it, then brakes; one that never expires drives on.
    expiring, free = _driving_robot(), _driving_robot()
    expiring.hold_goal_until(5 * PERIOD_NS + PERIOD_NS // 2)
    free.hold_goal_until(None)
    _drive(expiring, 8)
    _drive(free, 8)
    assert expiring.withdrawals == 1 and free.withdrawals == 0 and free.stack.has_path
    assert expiring.stack.state.x < free.stack.state.x - 0.05  # braked from 1.1 s on, not at 1.6 s
    braked_late = _driving_robot()
    braked_late.hold_goal_until(6 * PERIOD_NS)
    _drive(braked_late, 8)
    assert expiring.stack.state.x < braked_late.stack.state.x  # the split point counts, not just the step


def test_a_renewed_goal_is_not_withdrawn() -> None:
    robot = _driving_robot()
    for frame in range(10):
        robot.hold_goal_until(frame * PERIOD_NS + 5 * PERIOD_NS)  # each frame's status renews it
        robot.drive(frame * PERIOD_NS, (frame + 1) * PERIOD_NS)
    assert robot.withdrawals == 0 and robot.stack.has_path


def test_a_goal_whose_target_is_not_seen_starts_the_search_when_it_expires() -> None:
    robot = _driving_robot()
    robot.hold_goal_until(3 * PERIOD_NS, target_lost=True, target_place=np.array([3.0, 2.0, 0.9]))
    _drive(robot, 3)
    assert robot.search_phase == SEARCH_NONE and robot.searches == 0
    robot.drive(3 * PERIOD_NS, 4 * PERIOD_NS)
    assert robot.search_phase == SEARCH_LOOKING and robot.searches == 1 and robot.withdrawals == 1
    assert robot.clock_s == pytest.approx(0.8)
