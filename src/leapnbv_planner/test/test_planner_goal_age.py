from __future__ import annotations

import numpy as np
import pytest

from leapnbv_planner.floor_carry import carry_plane
from leapnbv_planner.goal_age import expired_age_s, too_old, valid_until_ns
from leapnbv_planner.inputs import CameraInMap

S = 1_000_000_000


def test_a_frame_is_too_old_only_past_a_positive_limit():
    assert not too_old(10 * S, 9 * S, 1.0)  # exactly at the limit: still current
    assert too_old(10 * S + 1, 9 * S, 1.0)
    assert not too_old(100 * S, 0, 0.0)  # 0: the rule is off


def test_a_goal_expires_with_its_age_past_the_limit():
    assert expired_age_s(10 * S, 9 * S, 1.0) is None
    assert expired_age_s(int(10.5 * S), 9 * S, 1.0) == pytest.approx(1.5)
    assert expired_age_s(100 * S, 0, 0.0) is None


def test_valid_until_is_the_last_instant_the_goal_stands():
    assert valid_until_ns(9 * S, 1.0) == 10 * S
    assert expired_age_s(valid_until_ns(9 * S, 1.0), 9 * S, 1.0) is None  # still current at valid_until
    assert expired_age_s(valid_until_ns(9 * S, 1.0) + 1, 9 * S, 1.0) is not None
    assert valid_until_ns(9 * S, 0.3) == 9 * S + 300_000_000  # no float32 rounding
    assert valid_until_ns(9 * S, 0.0) == 0  # no limit


def test_a_plane_carried_to_a_camera_moved_up_and_turned_keeps_the_world_floor():
    # Camera A 1.2 m above the floor, level; camera B 0.3 m higher and turned 90 degrees about the world z.
    level = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical -> world
    yaw = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    a = CameraInMap(level, np.array([1.0, 2.0, 1.2]))
    b = CameraInMap(yaw @ level, np.array([3.0, -1.0, 1.5]))
    normal, offset = carry_plane(np.array([0.0, -1.0, 0.0]), 1.2, a, b)
    np.testing.assert_allclose(normal, [0.0, -1.0, 0.0], atol=1e-12)  # up is still -y of the optical frame
    assert offset == pytest.approx(1.5, abs=1e-12)


def test_a_hidden_target_extends_the_age_limit_by_the_hold_and_no_limit_stays_none():
    from leapnbv_planner.goal_age import goal_age_limit_s

    assert goal_age_limit_s(1.0, 3.0, target_hidden=False) == 1.0
    assert goal_age_limit_s(1.0, 3.0, target_hidden=True) == 4.0
    assert goal_age_limit_s(1.0, 0.0, target_hidden=True) == 1.0
    assert goal_age_limit_s(0.0, 3.0, target_hidden=True) == 0.0  # offline runs: no limit, hidden or not
    # A goal 2.5 s old: withdrawn with the person in view, kept while they are hidden.
    assert expired_age_s(2_500_000_000, 0, goal_age_limit_s(1.0, 3.0, False)) == 2.5
    assert expired_age_s(2_500_000_000, 0, goal_age_limit_s(1.0, 3.0, True)) is None
