"""The simulated motion stack's kinematics: speed, acceleration, turn limits, paths replaced and withdrawn, the head."""
from __future__ import annotations

import math
from typing import List, Tuple

import numpy as np
import pytest

from leapnbv_sim.motion_stack import BaseLimits, BaseState, MotionStack, path_length, wrap_angle
from leapnbv_sim.poses import camera_heading, camera_pitch, camera_pose_from_base_goal

DT = 0.01
#: The tolerances these kinematics are checked at (tighter than the defaults, so the profiles show whole).
TIGHT = BaseLimits(goal_tolerance_m=0.05, heading_tolerance_rad=math.radians(3.0))


def drive(stack: MotionStack, until_s: float, dt: float = DT, stop_on_arrival: bool = True
          ) -> Tuple[float, List[Tuple[float, float, float, float]]]:
    """Step until arrival (or ``until_s``); (time taken, [(t, x, y, v)] per step)."""
    t, trace = 0.0, []
    while t < until_s - 1e-9:
        stack.step(dt)
        t += dt
        trace.append((t, stack.state.x, stack.state.y, stack.state.v))
        if stop_on_arrival and stack.arrived():
            break
    return t, trace


def test_straight_drive_is_a_trapezoid_at_the_limits() -> None:
    # 2 m at 0.5 m/s and 0.5 m/s^2: 1 s up (0.25 m), 3 s at speed (1.5 m), 1 s down (0.25 m) = 5 s.
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.2, TIGHT)
    stack.set_path(np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), 0.0)
    took, trace = drive(stack, 20.0)
    assert took == pytest.approx(5.0, abs=0.03)
    assert stack.state.x == pytest.approx(2.0, abs=0.005) and stack.state.y == pytest.approx(0.0, abs=1e-12)
    speeds = np.array([row[3] for row in trace])
    assert speeds.max() == pytest.approx(0.5, abs=1e-9)
    assert np.abs(np.diff(np.concatenate([[0.0], speeds]))).max() <= 0.5 * DT + 1e-12
    # Full speed from 1 s to 4 s: at 2.5 s it is 0.25 m + 1.5 s * 0.5 m/s = 1.0 m along.
    at = min(trace, key=lambda row: abs(row[0] - 2.5))
    assert at[1] == pytest.approx(1.0, abs=0.01) and at[3] == pytest.approx(0.5)
    assert stack.travelled_m == pytest.approx(2.0, abs=0.005)
    assert stack.base_arrived() and stack.remaining_m == pytest.approx(0.0, abs=0.01)


def test_a_short_drive_never_reaches_full_speed() -> None:
    # 0.18 m at 0.5 m/s^2: a triangle, peak sqrt(a d) = 0.3 m/s, 2 sqrt(d / a) = 1.2 s.
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.2, TIGHT)
    stack.set_path(np.array([[0.0, 0.0], [0.18, 0.0]]), 0.0)
    took, trace = drive(stack, 10.0)
    assert took == pytest.approx(1.2, abs=0.03)
    assert max(row[3] for row in trace) == pytest.approx(0.3, abs=0.01)


def test_turns_in_place_before_it_drives_and_at_the_turn_rate() -> None:
    # A goal 2 m to the left, to be faced to the left: it turns at 1 rad/s and rolls only once the carrot is
    # within 45 deg, at 0.785 s.
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.2, TIGHT)
    stack.set_path(np.array([[0.0, 0.0], [0.0, 2.0]]), math.pi / 2)
    drive(stack, 0.70, stop_on_arrival=False)
    assert stack.state.yaw == pytest.approx(0.70, abs=1e-6)
    assert (stack.state.x, stack.state.y, stack.state.v) == (0.0, 0.0, 0.0)
    took, _ = drive(stack, 20.0)
    assert stack.arrived() and stack.state.y == pytest.approx(2.0, abs=0.01)
    assert stack.state.yaw == pytest.approx(math.pi / 2, abs=math.radians(3.0))
    assert 0.70 + took == pytest.approx(0.785 + 5.0, abs=0.35)  # rolls, then the 2 m trapezoid (turning on)


def test_turning_to_the_final_heading_takes_angle_over_turn_rate() -> None:
    limits = BaseLimits(max_turn_rate_rad_s=0.5, goal_tolerance_m=0.05, heading_tolerance_rad=math.radians(3.0))
    stack = MotionStack(BaseState(1.0, 1.0, 0.0), 1.2, limits)
    stack.set_path(np.array([[1.0, 1.0]]), math.pi * 0.9)  # standing on the goal: turn only
    took, _ = drive(stack, 20.0)
    # Arrived once within the 3 deg heading tolerance: (0.9 pi - 3 deg) / 0.5 rad/s.
    assert took == pytest.approx((0.9 * math.pi - math.radians(3.0)) / 0.5, abs=0.015)
    assert (stack.state.x, stack.state.y) == (1.0, 1.0)


def test_a_withdrawn_goal_brakes_to_a_stop_at_the_deceleration_limit() -> None:
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.2, TIGHT)
    stack.set_path(np.array([[0.0, 0.0], [10.0, 0.0]]), 0.0)
    drive(stack, 2.0, stop_on_arrival=False)
    assert stack.state.v == pytest.approx(0.5)
    x_withdrawn = stack.state.x
    stack.clear_path()
    took, trace = drive(stack, 3.0, stop_on_arrival=False)
    stopped_at = next(row[0] for row in trace if row[3] == 0.0)
    assert stopped_at == pytest.approx(1.0, abs=DT + 1e-9)  # 0.5 m/s at 0.5 m/s^2
    assert stack.state.x - x_withdrawn == pytest.approx(0.25, abs=0.006)  # v^2 / 2a
    assert not stack.has_path and not stack.arrived()


def test_a_new_path_replaces_the_old_one_without_stopping() -> None:
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.2, TIGHT)
    stack.set_path(np.array([[0.0, 0.0], [4.0, 0.0]]), 0.0)
    drive(stack, 2.0, stop_on_arrival=False)
    here = stack.position_xy
    speed = stack.state.v
    stack.set_path(np.array([here, here + [1.0, 0.0], here + [1.0, 1.0]]), math.pi / 2)
    assert stack.state.v == speed == pytest.approx(0.5)  # taking the path does not reset the speed
    assert stack.remaining_m == pytest.approx(2.0)
    drive(stack, 20.0)
    assert stack.arrived()
    assert stack.position_xy == pytest.approx(here + [1.0, 1.0], abs=0.05)
    assert stack.state.x < 4.0 - 0.5  # the old goal was dropped: it never drove on to x = 4


def test_follows_a_corner_without_cutting_more_than_the_lookahead() -> None:
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.2, TIGHT)
    points = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]])
    stack.set_path(points, math.pi / 2)
    took, trace = drive(stack, 30.0)
    assert stack.arrived()
    xy = np.array([[row[1], row[2]] for row in trace])
    # Distance of every position to the L: within the lookahead (0.3 m), the corner cut at most that.
    dist = np.minimum(np.where(xy[:, 0] <= 2.0, np.abs(xy[:, 1]), np.hypot(xy[:, 0] - 2.0, xy[:, 1])),
                      np.where(xy[:, 1] >= 0.0, np.abs(xy[:, 0] - 2.0), np.inf))
    assert dist.max() < 0.3
    assert stack.travelled_m == pytest.approx(path_length(points), abs=0.3)
    assert took > 4.0 / 0.5  # 4 m at most at 0.5 m/s


def test_head_pans_and_tilts_at_its_rates_and_within_its_limit() -> None:
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.0)
    stack.look(math.pi / 2, 0.3)
    drive(stack, 0.2, stop_on_arrival=False)
    assert stack.state.pan == pytest.approx(1.5 * 0.2) and stack.state.tilt == pytest.approx(0.2)
    assert not stack.head_aligned()
    drive(stack, 1.0, stop_on_arrival=False)
    assert stack.state.pan == pytest.approx(math.pi / 2) and stack.state.tilt == pytest.approx(0.3)
    assert stack.head_aligned()
    camera = stack.camera_pose()
    assert camera_heading(camera) == pytest.approx(math.pi / 2) and camera_pitch(camera) == pytest.approx(0.3)
    assert camera.position == pytest.approx([0.0, 0.0, 1.0])
    stack.look(math.radians(178.0), 0.3)  # nearly behind: the pan stops at its 170 deg limit
    drive(stack, 3.0, stop_on_arrival=False)
    assert stack.state.pan == pytest.approx(math.radians(170.0))
    assert not stack.head_aligned()


def test_head_holds_its_world_heading_while_the_base_turns() -> None:
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.0, BaseLimits(max_turn_rate_rad_s=0.5, pan_rate_rad_s=2.0,
                                                                  heading_tolerance_rad=math.radians(3.0)))
    stack.look(0.0, 0.0)
    stack.set_path(np.array([[0.0, 0.0]]), 1.0)  # the base turns 1 rad in place
    drive(stack, 3.0)
    assert stack.state.yaw == pytest.approx(1.0, abs=math.radians(3.0))
    assert wrap_angle(stack.state.yaw + stack.state.pan) == pytest.approx(0.0, abs=0.02)
    assert stack.arrived()


def test_a_goal_just_behind_is_reached_not_driven_back_to() -> None:
    # Driving at 0.2 m/s, a goal planned one camera period ago 0.1 m behind (the view the plan was made from): within
    # the default 0.15 m tolerance the base brakes (0.04 m) and turns, it does not turn back.
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.2, BaseLimits(max_speed_m_s=0.2))
    stack.set_path(np.array([[0.0, 0.0], [10.0, 0.0]]), 0.0)
    drive(stack, 3.0, stop_on_arrival=False)
    x = stack.state.x
    stack.set_path(np.array([[x - 0.1, 0.0]]), 0.0)
    drive(stack, 5.0)
    assert stack.arrived() and stack.state.x == pytest.approx(x + 0.04, abs=0.002)
    # At 0.5 m/s braking takes 0.25 m, out of the tolerance: once it stands it drives back to the goal.
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.2)
    stack.set_path(np.array([[0.0, 0.0], [10.0, 0.0]]), 0.0)
    drive(stack, 3.0, stop_on_arrival=False)
    x = stack.state.x
    stack.set_path(np.array([[x - 0.1, 0.0]]), 0.0)
    drive(stack, 20.0)
    assert stack.arrived() and abs(stack.state.x - (x - 0.1)) <= 0.15


def test_from_camera_stands_under_the_camera() -> None:
    camera = camera_pose_from_base_goal(np.array([1.5, -0.5]), 2.0, 1.3, 0.2)
    stack = MotionStack.from_camera(camera)
    again = stack.camera_pose()
    assert again.position == pytest.approx(camera.position)
    assert again.rotation == pytest.approx(camera.rotation, abs=1e-12)
    assert stack.camera_height == pytest.approx(1.3) and stack.state.v == 0.0


def test_bad_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="max_speed_m_s"):
        BaseLimits(max_speed_m_s=0.0)
    with pytest.raises(ValueError, match="mounting height"):
        MotionStack(BaseState(0.0, 0.0, 0.0), 0.0)
    stack = MotionStack(BaseState(0.0, 0.0, 0.0), 1.0)
    with pytest.raises(ValueError, match="finite floor point"):
        stack.set_path(np.zeros((0, 2)), 0.0)
    with pytest.raises(ValueError, match="finite"):
        stack.set_path(np.array([[np.nan, 0.0]]), 0.0)
    with pytest.raises(ValueError, match="seconds"):
        stack.step(-0.1)
