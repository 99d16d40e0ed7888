"""The continuous evaluation's records: reversals and swaps counted, the JSON form lossless, the table's figures."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from leapnbv_evaluation.continuous_results import (
    OUTCOME_ARRIVED,
    OUTCOME_TIME_LIMIT,
    ContinuousEpisode,
    ContinuousRun,
    aggregate_continuous,
    continuous_table_markdown,
    count_reversals,
    count_swaps,
    per_episode_markdown,
)


def _line(start, end, steps):
    return np.linspace(start, end, steps)


def test_driving_back_is_a_reversal_a_gradual_turn_is_not() -> None:
    out = _line([0.0, 0.0], [1.0, 0.0], 21)
    back = _line([1.0, 0.0], [0.4, 0.0], 13)[1:]
    assert count_reversals(np.vstack([out, back])) == 1
    # Out, back and out again: two.
    again = _line([0.4, 0.0], [1.5, 0.0], 23)[1:]
    assert count_reversals(np.vstack([out, back, again])) == 2
    # A half circle of radius 1 m in 5 cm steps: 180 deg in all, never more than ~6 deg between 0.1 m pieces.
    angles = np.linspace(0.0, math.pi, 64)
    assert count_reversals(np.stack([np.cos(angles), np.sin(angles)], axis=1)) == 0
    # A right-angle corner turns 90 deg: below the 135 deg that counts.
    corner = np.vstack([out, _line([1.0, 0.0], [1.0, 1.0], 21)[1:]])
    assert count_reversals(corner) == 0
    # Standing still (and jitter under a piece's length) makes no pieces.
    assert count_reversals(np.zeros((50, 2)) + np.random.default_rng(0).normal(0, 0.001, (50, 2))) == 0


def test_target_swaps_count_taking_another_person_not_losing_the_target() -> None:
    assert count_swaps([1, 1, None, 1, 1]) == 0  # lost and found again: no swap
    assert count_swaps([None, None]) == 0
    assert count_swaps([1, None, 7, 7, 1]) == 1  # took person 7 (stayed on it: the same swap), then back
    assert count_swaps([7, 1]) == 1  # a wrong person from the first frame is a swap
    assert count_swaps([1, 7, 8, 1, 7]) == 3  # 7, then a third person, then 7 again
    assert count_swaps([3, 3], target=3) == 0


def _episode(seed, outcome, start, end, best, time_s, distance, first_path, switches, reversals=0):
    return ContinuousEpisode(
        seed=seed, scene_index=seed, start_stamp_ns=10**18 + seed, outcome=outcome, coverage_start=start,
        coverage_end=end, coverage_best=best, success=ContinuousEpisode.decide_success(start, end), time_s=time_s,
        distance_m=distance, first_path_m=first_path, first_goal_s=0.0, goal_switches=switches, withdrawals=0,
        reversals=reversals, target_swaps=0, frames=int(time_s * 5) + 1, frames_planned=int(time_s * 5),
        frames_failed=1, commit_reasons={"FIRST_GOAL": 1, "KEPT": 7}, wall_s=12.5)


def test_run_json_is_lossless_and_the_figures_are_the_episodes() -> None:
    run = ContinuousRun(room="corridor", obstacle_map=False, clock="lockstep", camera_rate_hz=5.0, time_limit_s=30.0,
                        commit_hold_s=1.0, episodes=[
                            _episode(0, OUTCOME_ARRIVED, 0.40, 0.80, 0.85, 8.0, 3.0, 2.5, 0),
                            _episode(1, OUTCOME_ARRIVED, 0.50, 0.55, 0.70, 12.0, 4.0, 4.0, 2, reversals=1),
                            _episode(2, OUTCOME_TIME_LIMIT, 0.60, 0.62, 0.66, 30.0, 1.0, None, 5)])
    again = ContinuousRun.from_json(json.loads(json.dumps(run.to_json())))
    assert again == run
    assert [e.success for e in run.episodes] == [True, False, False]  # +40 points; +5; +2
    a = aggregate_continuous(run)
    assert a["success_pct"] == pytest.approx(100.0 / 3) and a["arrived_pct"] == pytest.approx(200.0 / 3)
    assert a["time_to_arrival_median_s"] == pytest.approx(10.0)  # of the arrived ones: 8 and 12
    assert a["path_ratio_median"] == pytest.approx((3.0 / 2.5 + 1.0) / 2)
    assert a["goal_switches_median"] == 2.0 and a["goal_switches_max"] == 5.0
    assert a["reversals_total"] == 1.0 and a["episodes_with_reversal_pct"] == pytest.approx(100.0 / 3)
    table = continuous_table_markdown(run)
    assert "corridor, no map" in table and "| 3 | 33.3 % | 66.7 % |" in table
    assert per_episode_markdown(run).count("\n") == 2 + 3
    with pytest.raises(ValueError, match="format"):
        ContinuousRun.from_json({**run.to_json(), "format": 99})
