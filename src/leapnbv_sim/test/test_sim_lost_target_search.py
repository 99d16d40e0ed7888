"""The simulated motion stack's search for a lost target (DrivenRobot.lose_target): look, drive back, wait."""
from __future__ import annotations

import math

import numpy as np
import pytest

from leapnbv_sim.motion_stack import BaseLimits
from leapnbv_sim.poses import look_at_pose
from leapnbv_sim.simulator import (
    SEARCH_LOOKING,
    SEARCH_NONE,
    SEARCH_RETURNING,
    SEARCH_WAITING,
    DrivenRobot,
    SearchLimits,
)

DT = 0.05
LEVEL = np.eye(3)  # a path's final rotation only gives the heading: +x here (the camera's x axis along world +x)


def _robot(search: SearchLimits) -> DrivenRobot:
    # The camera 1.2 m up at the origin, looking along +x.
    start = look_at_pose(np.array([0.0, 0.0, 1.2]), np.array([5.0, 0.0, 1.2]))
    return DrivenRobot(start, BaseLimits(), search=search)


def _drive_out(robot: DrivenRobot, seen_until_x: float, to_x: float = 2.0) -> None:
    """Follow a straight path to (to_x, 0), telling the robot it saw the target while x <= seen_until_x."""
    path = np.array([[0.0, 0.0, 0.0], [to_x, 0.0, 0.0]])
    rotation = look_at_pose(np.array([to_x, 0.0, 1.2]), np.array([to_x + 1.0, 0.0, 1.2])).rotation
    assert robot.take_path(path, rotation, goal_changed=True)
    for _ in range(400):
        camera = robot.advance(DT)
        if camera.position[0] <= seen_until_x:
            robot.saw_target_from(camera.position)
        if robot.stack.state.x >= to_x - 0.3:  # lost on the way, still driving
            return
    pytest.fail("the robot did not get there")


def _run(robot: DrivenRobot, seconds: float) -> list:
    phases = []
    for _ in range(int(round(seconds / DT))):
        robot.advance(DT)
        phases.append(robot.search_phase)
    return phases


def test_a_lost_target_is_looked_for_then_driven_back_to_where_it_was_seen() -> None:
    robot = _robot(SearchLimits(look_s=1.5, return_m=3.0, back_off_m=0.0))
    _drive_out(robot, seen_until_x=0.8)
    moving = robot.stack.state.v
    assert moving > 0.1
    robot.lose_target(np.array([3.0, 2.0, 0.9]))  # last known place: ahead on the left
    assert robot.search_phase == SEARCH_LOOKING and robot.searches == 1 and robot.withdrawals == 1
    robot.lose_target(np.array([3.0, 2.0, 0.9]))  # the same loss restated: the same search
    assert robot.searches == 1 and robot.withdrawals == 1
    phases = _run(robot, 1.4)
    assert set(phases) == {SEARCH_LOOKING}
    # It brakes (0.5 m/s at 0.5 m/s^2: 1 s; never drives on) and the head turns toward the last known place.
    s = robot.stack.state
    assert s.v == pytest.approx(0.0, abs=1e-9)
    bearing = math.atan2(2.0 - s.y, 3.0 - s.x)
    assert abs(math.remainder(s.yaw + s.pan - bearing, 2 * math.pi)) < math.radians(5.0)
    stopped_x = s.x
    phases = _run(robot, 20.0)
    assert SEARCH_RETURNING in phases and phases[-1] == SEARCH_WAITING
    # Back at the track's point nearest the last place it saw the target from (x 0.8, within a step's travel).
    assert robot.stack.state.x == pytest.approx(0.8, abs=0.06) and robot.stack.state.x < stopped_x - 0.5
    s = robot.stack.state
    assert abs(s.y) < 0.1  # it turned round to drive back (a base never drives backwards): a pursuit's offset
    # ... and stands facing the target's last known place.
    assert abs(math.remainder(s.yaw - math.atan2(2.0 - s.y, 3.0 - s.x), 2 * math.pi)) < math.radians(5.0)
    assert robot.stack.travelled_m > 2 * (stopped_x - 0.8) - 0.1  # drove out and back


def test_the_drive_back_is_bounded_and_a_new_goal_ends_the_search() -> None:
    robot = _robot(SearchLimits(look_s=0.5, return_m=0.4, back_off_m=1.0))
    _drive_out(robot, seen_until_x=0.3)
    robot.lose_target()
    _run(robot, 2.0)  # stop and look
    stopped_x = float(robot._track[-1][0])
    _run(robot, 15.0)
    assert robot.search_phase == SEARCH_WAITING
    back = stopped_x - robot.stack.state.x
    assert 0.3 <= back <= 0.4 + 0.06  # at most return_m along its track, not to x 0.3
    # A new CURRENT goal's path ends it.
    assert robot.take_path(np.array([[robot.stack.state.x, 0.0, 0.0], [2.5, 0.0, 0.0]]), LEVEL, goal_changed=True)
    assert robot.search_phase == SEARCH_NONE
    # So does a withdrawal with the target in view again.
    robot.lose_target()
    assert robot.search_phase == SEARCH_LOOKING and robot.searches == 2
    robot.withdraw()
    assert robot.search_phase == SEARCH_NONE


@pytest.mark.parametrize("back_off_m", [0.5, 5.0])
def test_the_drive_back_goes_back_off_m_beyond_the_last_seen_from_place(back_off_m) -> None:
    robot = _robot(SearchLimits(look_s=0.5, return_m=3.0, back_off_m=back_off_m))
    _drive_out(robot, seen_until_x=1.0)  # 1.7 m out, lost at about x 1.7, braked to about 1.95
    robot.lose_target()
    _run(robot, 20.0)
    assert robot.search_phase == SEARCH_WAITING
    # 0.5 m past x 1.0 toward the start (within a step's travel); 5 m: as far as the track goes, its start
    assert robot.stack.state.x == pytest.approx(0.5 if back_off_m < 1.0 else 0.0, abs=0.06)


def test_without_a_place_to_go_back_to_it_only_looks() -> None:
    never_seen = _robot(SearchLimits(look_s=0.5, return_m=3.0))
    _drive_out(never_seen, seen_until_x=-1.0)  # never saw the target from anywhere
    never_seen.lose_target()
    assert _run(never_seen, 3.0)[-1] == SEARCH_WAITING
    only_looks = _robot(SearchLimits(look_s=0.5, return_m=0.0))
    _drive_out(only_looks, seen_until_x=1.0)
    only_looks.lose_target()
    x = only_looks.stack.state.x
    phases = _run(only_looks, 3.0)
    assert SEARCH_RETURNING not in phases and phases[-1] == SEARCH_WAITING
    assert only_looks.stack.state.x >= x  # braking only carries it forward
    with pytest.raises(ValueError, match="look_s"):
        SearchLimits(look_s=-1.0)
    with pytest.raises(ValueError, match="return_m"):
        SearchLimits(return_m=float("nan"))
    with pytest.raises(ValueError, match="back_off_m"):
        SearchLimits(back_off_m=-0.1)
